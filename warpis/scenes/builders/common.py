"""What the scene generators share: mesh and TOML writing, receiver classification,
the geometry of Veach's plates, and the check that a regenerated tree matches the
committed one.

:mod:`.mesh_scenes` (``scripts/make_scenes.py``) and :mod:`.mitsuba_scenes`
(``scripts/make_mitsuba_scenes.py``) write byte-identical files on every run: fixed float
formatting (:func:`clean`), fixed seeds, no timestamps.  Their verification tolerances
are their own (one absolute, one relative to the scene's size) and live in their modules.
"""

from __future__ import annotations

import filecmp
import json
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

FloatArray = np.ndarray
IntArray = np.ndarray

# A receiver is lit by an emitter when it sees more than LIT_FRACTION of the emitter's
# samples, in its umbra below UMBRA_FRACTION, in penumbra between (fractions of samples,
# no units: the same for both generators).
LIT_FRACTION = 0.99
UMBRA_FRACTION = 0.01


# ---------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------


def unit(v: ArrayLike) -> FloatArray:
    """Return ``v`` normalised along its last axis."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def quad(center: ArrayLike, edge_u: ArrayLike,
         edge_v: ArrayLike) -> tuple[FloatArray, IntArray]:
    """Build a two-triangle quad whose front normal is ``edge_u x edge_v``.

    Parameters
    ----------
    center, edge_u, edge_v : array_like, shape (3,)
        Quad centre and its two full-length edge vectors.

    Returns
    -------
    vertices : ndarray, shape (4, 3)
    faces : ndarray, shape (2, 3)
    """
    c, u, v = (np.asarray(a, dtype=np.float64) for a in (center, edge_u, edge_v))
    vertices = np.array([c - u / 2 - v / 2, c + u / 2 - v / 2,
                         c + u / 2 + v / 2, c - u / 2 + v / 2])
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    return vertices, faces


# ---------------------------------------------------------------------------
# Veach's plates (Veach 1997, fig. 9.2): the geometry both generators write
# ---------------------------------------------------------------------------

VEACH_CAMERA = np.array([0.0, -15.0, 6.5])
VEACH_LIGHT_ROW = np.array([0.0, 0.0, 4.5])
VEACH_LIGHT_X = (-3.75, -1.25, 1.25, 3.75)
VEACH_PLATES = ((-4.0, 0.5), (-3.0, 0.9), (-2.0, 1.3), (-1.0, 1.7))  # (y, z) of centres
VEACH_PLATE_SIZE = (9.0, 0.6)


def veach_plate(center: FloatArray) -> tuple[FloatArray, FloatArray, IntArray]:
    """Plate normal (mirror from the camera to the light row) and its quad."""
    to_camera = unit(VEACH_CAMERA - center)
    to_light = unit(VEACH_LIGHT_ROW - center)
    normal = unit(to_camera + to_light)
    x_axis = np.array([1.0, 0.0, 0.0])
    depth = np.cross(normal, x_axis)  # x_axis x depth == normal
    vertices, faces = quad(center, VEACH_PLATE_SIZE[0] * x_axis, VEACH_PLATE_SIZE[1] * depth)
    return normal, vertices, faces


# ---------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------


def clean(values: ArrayLike, decimals: int = 6) -> FloatArray:
    """Round to ``decimals`` and turn negative zeros into zeros."""
    return np.round(np.asarray(values, dtype=np.float64), decimals) + 0.0


def write_obj(path: Path, vertices: FloatArray, faces: IntArray) -> None:
    """Write a triangle mesh as OBJ text with fixed ``%.6f`` formatting."""
    lines = [f"# warpis scene mesh: {len(vertices)} vertices, {len(faces)} triangles"]
    lines += ["v %.6f %.6f %.6f" % tuple(v) for v in clean(vertices)]
    lines += ["f %d %d %d" % tuple(f) for f in np.asarray(faces) + 1]
    path.write_text("\n".join(lines) + "\n", encoding="ascii", newline="\n")


def write_ply(path: Path, vertices: FloatArray, faces: IntArray) -> None:
    """Write a triangle mesh as minimal binary little-endian PLY."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    records = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
    records["n"] = 3
    records["idx"] = faces
    with path.open("wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(clean(vertices).astype("<f4").tobytes())
        fh.write(records.tobytes())


def write_mesh(path: Path, vertices: FloatArray, faces: IntArray) -> None:
    """Write a mesh as OBJ or binary PLY according to the file suffix."""
    writers = {".obj": write_obj, ".ply": write_ply}
    writers[path.suffix](path, vertices, faces)


def toml_value(value: Any) -> str:
    """Format a value as TOML (strings, numbers, arrays, inline tables)."""
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(clean(value)))
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + " }"
    return "[" + ", ".join(toml_value(v) for v in value) + "]"


def toml_points(points: FloatArray) -> str:
    """Format receiver points as a multi-line TOML array."""
    rows = "".join(f"    {toml_value([float(c) for c in p])},\n" for p in points)
    return f"points = [\n{rows}]"


# ---------------------------------------------------------------------------
# Receiver classification
# ---------------------------------------------------------------------------


def visibility_label(fraction: float | None) -> str:
    """Classify a visible fraction as lit, penumbra, umbra or below-horizon
    (``LIT_FRACTION``, ``UMBRA_FRACTION``)."""
    if fraction is None:
        return "below-horizon"
    if fraction > LIT_FRACTION:
        return "lit"
    return "umbra" if fraction < UMBRA_FRACTION else "penumbra"


# ---------------------------------------------------------------------------
# Regenerated files against the committed ones
# ---------------------------------------------------------------------------


def diff_trees(fresh: Path, committed: Path, names: Sequence[str]) -> list[str]:
    """List the files of the scenes ``names`` that differ between two scene roots."""
    problems = []
    for name in names:
        a, b = fresh / name, committed / name
        names_a = {p.name for p in a.iterdir()}
        names_b = {p.name for p in b.iterdir()} if b.is_dir() else set()
        problems += [f"{name}/{f}: missing" for f in sorted(names_a - names_b)]
        problems += [f"{name}/{f}: not generated" for f in sorted(names_b - names_a)]
        problems += [f"{name}/{f}: differs" for f in sorted(names_a & names_b)
                     if not filecmp.cmp(a / f, b / f, shallow=False)]
    return problems


def check_tree(root: Path, write: Callable[[Path], None], names: Sequence[str]) -> int:
    """Regenerate the scenes ``names`` with ``write`` into a temporary folder and compare with ``root``.

    Prints each differing file and a verdict; returns the exit status (1 if any differ).
    """
    with tempfile.TemporaryDirectory() as tmp:
        write(Path(tmp))
        problems = diff_trees(Path(tmp), root, names)
    for line in problems:
        print(line)
    print("scenes differ from a fresh generation" if problems else "scenes are up to date")
    return 1 if problems else 0
