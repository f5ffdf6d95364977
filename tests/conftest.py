"""Shared fixtures and helpers: scene files written on the fly, bundled scenes loaded once.

``write_scene(directory, meshes=..., receivers=..., material=...)`` writes mesh files and
a scene TOML (see docs/scene-files.md) and returns the TOML's path.  Every key of a
mesh entry goes into its ``[[mesh]]`` table verbatim, except three that say what to
write at ``path``: ``vertices`` and ``faces`` (geometry, written in the format of the
path's suffix), or ``content`` (bytes or text, written as is).  Values are written as
TOML literals, so a test can put any value (``nan``, ``inf``, unknown keys, wrong types)
anywhere in a scene file.

Tests import the helpers directly (``from conftest import quad, write_scene``) or take
the ``write_scene`` fixture.  ``cli`` runs ``warpis.cli.main`` in-process with captured
output; ``run_warpis`` runs the command in a fresh Python process.
"""

from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# OpenBLAS's threads spin while they wait for work: beside pytest-xdist's two workers and
# warpis's own threads they only take the cores from the kernels (the chi-square tests of
# test_techniques.py: 112 s of CPU with a BLAS thread per core, 80 s with one).  One BLAS
# thread per process, set before numpy loads; the processes the tests start inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _keep_freed_memory() -> None:
    """Serve the tests' large numpy arrays from memory the process already holds.

    glibc maps each allocation above its mapping threshold (which grows to at most 32 MiB)
    afresh and unmaps it when freed, and numpy asks for huge pages (madvise) on its large
    arrays: every chi-square case (a million
    directions, grids of 1.8 million cells, float64 (k, 3) temporaries of 24–44 MiB) paid
    the kernel for zeroing — and compacting memory for — new pages at first touch.  With
    both off, the 12 chi-square cases of occluded-quad take 11 s of wall time and 0.45 s
    of system time instead of 19 s and 10 s, at the same peak memory; a process that
    allocates and frees a 40 MiB array again and again takes 10,241 page faults per array
    with glibc's defaults, none with these.  Set in the environment for the processes the
    tests start (xdist's workers among them: glibc and numpy read these when they load),
    and through mallopt for this one."""
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    threshold = str(1 << 30)  # above any array of the suite: nothing large is mapped apart
    os.environ.setdefault("MALLOC_MMAP_THRESHOLD_", threshold)
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", threshold)
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        libc.mallopt(-3, int(os.environ["MALLOC_MMAP_THRESHOLD_"]))  # M_MMAP_THRESHOLD
        libc.mallopt(-1, int(os.environ["MALLOC_TRIM_THRESHOLD_"]))  # M_TRIM_THRESHOLD
    except (AttributeError, OSError, TypeError, ValueError):  # not glibc: its defaults stand
        pass


_keep_freed_memory()

import numpy as np  # after the BLAS and memory settings
import pytest
import trimesh

import warpis
from warpis.check.mitsuba_bsdfs import LLVM_GLOB, llvm_library

# Mitsuba's llvm_ad_rgb variant (Mitsuba's side of the array comparisons and of the
# benchmark) needs libLLVM 19: the system's 14 and 15 abort it.  ``LLVM``: its path (also
# exported as DRJIT_LIBLLVM_PATH), None without one; tests that need it skip, saying why.
LLVM = llvm_library()
needs_llvm = pytest.mark.skipif(
    LLVM is None,
    reason=f"Mitsuba's llvm_ad_rgb variant needs libLLVM 19: DRJIT_LIBLLVM_PATH is unset and nothing matches "
           f"{LLVM_GLOB}")

# warpis keeps built BVHs and theory results on disk (warpis/kernels/bvh.py,
# warpis/analysis/memo.py).  A test run uses a folder of its own: the run's first process
# (pytest-xdist's controller, or pytest without workers) makes it and removes it at exit;
# the workers and every warpis process the tests start inherit it, so a BVH or an exact
# variance is computed once per run, not once per worker.
if "WARPIS_TEST_CACHE_DIR" not in os.environ:
    os.environ["WARPIS_TEST_CACHE_DIR"] = tempfile.mkdtemp(prefix="warpis-test-cache-")
    atexit.register(shutil.rmtree, os.environ["WARPIS_TEST_CACHE_DIR"], True)
os.environ["WARPIS_CACHE_DIR"] = os.environ["WARPIS_TEST_CACHE_DIR"]

# The files that hold the suite's longest tests (10–50 s each: unbiasedness per scene,
# the verdict fixture, Mitsuba comparisons, kernels compiled from plugins), longest
# first.  They run first, whole and in their own order: pytest-xdist hands out the first
# quarter of the tests alternately, so the long ones overlap on the two workers and the
# many short ones fill the end: none of the long ones is left for one worker to finish
# while the other waits.  A new test of tens of seconds belongs in one of these files, or
# its file in this list.
RUN_FIRST = ("test_estimators.py", "test_verify_verdicts.py", "test_theory.py", "test_check.py",
             "test_sphere_lights.py", "test_against_mitsuba.py", "test_user_pattern.py", "test_material_preview.py",
             "test_image_against_mitsuba.py", "test_techniques.py")


def pytest_collection_modifyitems(config, items):
    first = {name: rank for rank, name in enumerate(RUN_FIRST)}
    items.sort(key=lambda item: first.get(item.path.name, len(RUN_FIRST)))  # stable: a file's order is kept


BUNDLED = ("heavy-occluder", "occluded-quad", "two-lights", "veach-plates")  # TOML scenes
# Mitsuba XML scenes (need the mitsuba extra; tests/test_mitsuba_scene.py and test_against_mitsuba.py)
MITSUBA_BUNDLED = ("mitsuba-cornell-box", "mitsuba-material-preview", "mitsuba-veach-plates")
# TOML scenes whose receivers are a camera's pixels (thousands: kept out of BUNDLED's per-scene tests)
CAMERA_BUNDLED = ("veach-plates-camera",)

# The default material and receivers of write_scene: irradiance at the origin, facing +z.
IRRADIANCE = {"type": "irradiance"}
ONE_RECEIVER = {"points": [[0.0, 0.0, 0.0]], "normal": [0.0, 0.0, 1.0]}

_MESH_FILE_KEYS = ("vertices", "faces", "content")
_DEFAULT = object()


# --------------------------------------------------------------------------- geometry


def quad(center=(0.0, 0.0, 0.0), half: float | tuple[float, float] = 0.5, facing: str = "down"):
    """Horizontal rectangle as two triangles: (vertices (4, 3), faces (2, 3)).

    ``half`` is the half-size (one number, or (x, y)); ``facing`` is ``"down"`` (front
    face towards −z, as a ceiling light) or ``"up"`` (towards +z, as a floor).
    """
    hx, hy = (half, half) if np.isscalar(half) else half
    v = np.array([[-hx, -hy, 0.0], [-hx, hy, 0.0], [hx, hy, 0.0], [hx, -hy, 0.0]]) + np.asarray(center, float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    if facing == "up":
        f = f[:, ::-1].copy()
    elif facing != "down":
        raise ValueError(f"facing must be 'up' or 'down', got {facing!r}")
    return v, f


def floor_entry(path: str = "floor.obj", half: float = 2.0, **keys: Any) -> dict[str, Any]:
    """A [[mesh]] entry: a 2·half square floor at z = 0 facing up."""
    v, f = quad((0.0, 0.0, 0.0), half, "up")
    return {"path": path, "vertices": v, "faces": f, **keys}


def light_entry(path: str = "light.obj", emission: float = 10.0, height: float = 1.0, half: float = 0.5,
                **keys: Any) -> dict[str, Any]:
    """A [[mesh]] entry: a 2·half square light at z = height facing down, radiance ``emission``."""
    v, f = quad((0.0, 0.0, height), half, "down")
    return {"path": path, "vertices": v, "faces": f, "emission": emission, **keys}


def concat_meshes(meshes: list[tuple[np.ndarray, np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, radiance) of several meshes → one scene's vertices, triangles and
    per-triangle emission, for ``Scene.from_arrays``."""
    verts, faces, emission, offset = [], [], [], 0
    for v, f, radiance in meshes:
        verts.append(np.asarray(v, dtype=float))
        faces.append(np.asarray(f) + offset)
        emission += [radiance] * len(f)
        offset += len(v)
    return np.vstack(verts), np.vstack(faces), np.array(emission, dtype=float)


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a triangle mesh in the format of ``path``'s suffix.

    OBJ is written by hand with ``repr`` floats (exact round trip, and NaN or infinite
    coordinates survive); every other format goes through trimesh's exporter.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if path.suffix.lower() == ".obj":
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
        lines += ["f " + " ".join(str(i + 1) for i in face) for face in faces.tolist()]
        path.write_text("\n".join(lines) + "\n")
    else:
        trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


# --------------------------------------------------------------------------- TOML


def toml_value(value: Any) -> str:
    """A Python value as a TOML literal (dicts become inline tables)."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, Path):
        return json.dumps(str(value))
    if isinstance(value, (list, tuple, np.ndarray)):
        items = value.tolist() if isinstance(value, np.ndarray) else value
        return "[" + ", ".join(toml_value(v) for v in items) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"no TOML literal for {value!r}")


def toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _table(header: str, table: dict[str, Any]) -> list[str]:
    return [header] + [f"{toml_key(k)} = {toml_value(v)}" for k, v in table.items()] + [""]


def write_scene(directory: Path, meshes: list[dict[str, Any]] | None = None,
                receivers: dict | list[dict] | None = None, material: dict | None = _DEFAULT,
                name: str | None = "test-scene", extra: dict[str, Any] | None = None,
                filename: str = "scene.toml", spheres: list[dict[str, Any]] | None = None) -> Path:
    """Write mesh files and a scene TOML under ``directory``; return the TOML's path.

    Parameters
    ----------
    meshes
        ``[[mesh]]`` entries (default: :func:`floor_entry` and :func:`light_entry`).
        ``vertices``/``faces`` or ``content`` in an entry are written to its ``path``
        (relative to ``directory``) and left out of the TOML; an entry without them
        names a file that must already exist, or that a test means to be missing.
    receivers
        One ``[receivers]`` table (a dict) or several ``[[receivers]]`` (a list of
        dicts); default: one point at the origin with normal +z.
    material
        The ``[material]`` table (default irradiance); ``None`` leaves it out.
    name
        The scene's ``name``; ``None`` leaves it out.
    extra
        More top-level keys, written before the tables.
    spheres
        ``[[sphere]]`` tables, written verbatim after the meshes.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if meshes is None:
        meshes = [floor_entry(), light_entry()]
    if receivers is None:
        receivers = ONE_RECEIVER
    if material is _DEFAULT:
        material = IRRADIANCE
    top = ({"name": name} if name is not None else {}) | (extra or {})
    lines = [f"{toml_key(k)} = {toml_value(v)}" for k, v in top.items()] + [""]
    for entry in meshes:
        entry = dict(entry)
        if "vertices" in entry or "faces" in entry:
            write_mesh(directory / entry["path"], entry.pop("vertices"), entry.pop("faces"))
        elif "content" in entry:
            target = directory / entry["path"]
            target.parent.mkdir(parents=True, exist_ok=True)
            data = entry.pop("content")
            target.write_bytes(data if isinstance(data, bytes) else data.encode())
        lines += _table("[[mesh]]", entry)
    for entry in spheres or []:
        lines += _table("[[sphere]]", entry)
    if isinstance(receivers, dict):
        lines += _table("[receivers]", receivers)
    else:
        for group in receivers:
            lines += _table("[[receivers]]", group)
    if material is not None:
        lines += _table("[material]", material)
    path = directory / filename
    path.write_text("\n".join(lines))
    return path


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(name="write_scene")
def write_scene_fixture():
    """:func:`write_scene` itself: ``write_scene(tmp_path, meshes=..., ...)`` → scene TOML path."""
    return write_scene


@pytest.fixture(scope="session")
def loaded_scenes() -> dict[str, warpis.Scene]:
    """Every bundled TOML scene, loaded once per test session on the CPU (name → Scene)."""
    return {name: warpis.load_scene(name) for name in BUNDLED}


@pytest.fixture(scope="session", params=BUNDLED)
def bundled_scene(request, loaded_scenes) -> warpis.Scene:
    """Each bundled scene in turn (parametrised by name), from the session's cache."""
    return loaded_scenes[request.param]


# --------------------------------------------------------------------------- command line


@dataclass
class CliResult:
    """Exit status and captured output of one ``warpis`` run."""

    status: int
    out: str
    err: str

    @property
    def err_lines(self) -> list[str]:
        return self.err.splitlines()


def one_error_line(result: CliResult) -> str:
    """The single ``warpis: error:`` line of a failed run: exit 2, nothing on stdout, no
    traceback, exactly one line on stderr."""
    assert result.status == 2, (result.status, result.err)
    assert result.out == ""
    assert len(result.err_lines) == 1, result.err
    assert "Traceback" not in result.err
    line = result.err_lines[0]
    assert line.startswith("warpis: error: "), line
    return line


def run_warpis(*args: str, timeout: float = 300) -> CliResult:
    """Run ``python -m warpis.cli ARGS`` in a fresh process (the real console behaviour)."""
    proc = subprocess.run([sys.executable, "-m", "warpis.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)
    return CliResult(proc.returncode, proc.stdout, proc.stderr)


@pytest.fixture
def cli(capsys):
    """``cli(*args)`` runs ``warpis.cli.main(args)`` in this process → :class:`CliResult`.

    argparse's exits (``--help``, usage errors) become the status, as in a real process.
    """
    from warpis.cli import main

    def run(*args: str) -> CliResult:
        capsys.readouterr()
        try:
            status = main([str(a) for a in args])
        except SystemExit as exc:
            status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        captured = capsys.readouterr()
        return CliResult(status, captured.out, captured.err)

    return run


def tessellated_veach_plates(folder: Path) -> Path:
    """veach-plates with its sphere lights as 320-triangle icospheres (the bundled scene's
    lights before they were analytic): triangle lights that every ray crosses twice,
    for the tests of light pdfs over many emitter triangles.  Returns the scene file."""
    import tomllib

    source = Path(warpis.__file__).resolve().parent.parent / "meshes" / "veach-plates"
    if not source.is_dir():
        from warpis.scenes import resolve_scene_path

        source = resolve_scene_path("veach-plates").parent
    doc = tomllib.loads((source / "scene.toml").read_text())
    folder.mkdir(parents=True, exist_ok=True)
    for m in doc["mesh"]:
        shutil.copy(source / m["path"], folder / m["path"])
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    write_mesh(folder / "light_sphere.obj", np.asarray(ico.vertices), np.asarray(ico.faces))
    meshes = list(doc["mesh"]) + [{"path": "light_sphere.obj", "emission": s["emission"],
                                   "transform": {"translate": s["center"], "scale": s["radius"]}}
                                  for s in doc["sphere"]]
    return write_scene(folder, meshes=meshes, receivers=doc["receivers"], material=None, name="veach-plates")


def dome_scene(folder: Path, radiance: float) -> warpis.Scene:
    """One upward receiver at the centre of a closed, inward-facing icosphere of uniform
    ``radiance`` (radius 50, irradiance material): f = L cos θ, F = πL."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    sphere.invert()  # front faces inwards
    sphere.export(folder / "dome.obj")
    (folder / "scene.toml").write_text(
        f'name = "dome"\n[[mesh]]\npath = "dome.obj"\nemission = {radiance}\n'
        '[receivers]\npoints = [[0.0, 0.0, 0.0]]\nnormal = [0.0, 0.0, 1.0]\n[material]\ntype = "irradiance"\n')
    return warpis.load_scene(folder / "scene.toml")


def sky_environment(height: int = 12, width: int = 24, angle: float = 0.7) -> warpis.Environment:
    """A small procedural sky for scenes written in tests: a gradient from the zenith to a
    black lower hemisphere in some longitudes (cells of zero radiance), and a sun 20× the
    sky over four texels; rotated by ``angle`` about a tilted axis (a general rotation)."""
    theta = np.pi * np.arange(height) / (height - 1)
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    sky = 0.5 + 1.5 * np.cos(theta / 2)[:, None] ** 2 * (1.0 + 0.3 * np.sin(phi)[None, :])
    sky[theta > 0.6 * np.pi, : width // 3] = 0.0
    sky[2:4, 5:7] *= 20.0
    axis = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    return warpis.Environment(texels=sky, rotation=rotation, label="sky")


# --------------------------------------------------------------------------- point-set forms
# ``values`` callables for the pair forms of warpis.point_sets on closed-form ψ.

BELOW_ONE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))  # the largest float32 below 1


def float32_points(u: np.ndarray) -> np.ndarray:
    """The points as theory.py passes them on: within the call limit, inside [0,1)² before
    and after the cast to float32."""
    from warpis.point_sets import MAX_POINTS_PER_CALL

    assert u.ndim == 2 and u.shape[1] == 2 and 0 < len(u) <= MAX_POINTS_PER_CALL
    assert (u >= 0).all() and (u <= BELOW_ONE).all()
    u = u.astype(np.float32).astype(np.float64)
    assert (u < 1).all()
    return u


def one_technique(funcs, cast: bool = True):
    """values(u) of one technique per receiver: receiver r's ψ is funcs[r] (``cast``: at
    the float32 points the kernel would see)."""
    def values(u):
        u = float32_points(u) if cast else u
        f = np.stack([fn(u[:, 0], u[:, 1]) for fn in funcs])
        return f, f * f
    return values


def mixture(a, b):
    """values(u) of a random pick between ψ = a and ψ = b (each with probability 1/2)."""
    def values(u):
        u = float32_points(u)
        fa, fb = a(u[:, 0], u[:, 1]), b(u[:, 0], u[:, 1])
        return ((fa + fb) / 2)[None], ((fa * fa + fb * fb) / 2)[None]
    return values
