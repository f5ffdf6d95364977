"""The TOML scenes bundled with warpis (``scripts/make_scenes.py``): their builders,
their writer and the verification of what was written.

Each scene folder holds a ``scene.toml`` and the mesh files it names.  The builders are
deterministic (fixed seeds, fixed float formatting, no timestamps), so the committed
output can be checked against a fresh run (:func:`check`).

After writing, every scene is read back from disk and verified with trimesh ray
casting (:func:`verify_scene`): visible fraction of each emitter from each receiver,
winding and orientation of every mesh, emitter facing, and receivers lying on a
surface.  Distances here are absolute, in the scenes' units (the scenes span a few
units): ``RAY_OFFSET_ABSOLUTE``, ``SURFACE_TOLERANCE_ABSOLUTE``.
"""

from __future__ import annotations

import shutil
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from .common import (VEACH_CAMERA, VEACH_LIGHT_ROW, VEACH_LIGHT_X, VEACH_PLATES, FloatArray, IntArray, check_tree,
                     quad, toml_points, toml_value, unit, veach_plate, visibility_label, write_mesh)

SCENE_NAMES = ("occluded-quad", "two-lights", "veach-plates", "heavy-occluder")

MESH_VISIBILITY_SAMPLES = 2000  # points on each emitter for a receiver's visible fraction
RAY_OFFSET_ABSOLUTE = 1e-4  # shadow rays start this far (scene units) along the receiver's normal
SURFACE_PROBE_ABSOLUTE = 1e-3  # a receiver's surface is found by a ray from this far (scene units) above it
SURFACE_TOLERANCE_ABSOLUTE = 1e-5  # receiver to its triangle's plane, in scene units


# ---------------------------------------------------------------------------
# Scene description
# ---------------------------------------------------------------------------


@dataclass
class MeshEntry:
    """One ``[[mesh]]`` entry of a scene file.

    Attributes
    ----------
    path : str
        Mesh file name, relative to the scene file.
    emission : float or None
        Radiance of the front face, or None for a non-emitting mesh.
    transform : dict or None
        Optional ``{translate, scale, rotate}`` transform.
    """

    path: str
    emission: float | None = None
    transform: dict[str, Any] | None = None


@dataclass
class SphereEntry:
    """One ``[[sphere]]`` entry of a scene file: an analytic sphere (emitting where
    ``emission`` is given)."""

    center: tuple[float, float, float]
    radius: float
    emission: float | None = None


@dataclass
class ReceiverGroup:
    """One group of receivers sharing a normal and a material.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
        Receiver positions, on their surface.
    normal : ndarray, shape (3,)
        Common normal, pointing to the lit side.
    name : str or None
        Optional group name.
    material : dict or None
        Optional material overriding the scene default.
    """

    points: FloatArray
    normal: FloatArray
    name: str | None = None
    material: dict[str, Any] | None = None


@dataclass
class Scene:
    """A scene to be written: mesh files, mesh entries and receivers.

    Attributes
    ----------
    name : str
        Scene (and folder) name.
    description : str
        One-line description.
    files : dict of str to (vertices, faces)
        Mesh data by file name; the suffix selects OBJ or binary PLY.
    meshes : list of MeshEntry
        Mesh entries in scene order (a file may be instanced several times).
    receivers : list of ReceiverGroup
        Receiver groups.
    material : dict or None
        Default material, or None to leave it out.
    spheres : list of SphereEntry
        Analytic spheres, after the meshes.
    """

    name: str
    description: str
    files: dict[str, tuple[FloatArray, IntArray]]
    meshes: list[MeshEntry]
    receivers: list[ReceiverGroup]
    material: dict[str, Any] | None = None
    spheres: list[SphereEntry] = field(default_factory=list)

# ---------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------


def box(extents: ArrayLike,
        center: ArrayLike = (0.0, 0.0, 0.0)) -> tuple[FloatArray, IntArray]:
    """Build a closed, outward-wound axis-aligned box of 12 triangles."""
    mesh = trimesh.creation.box(extents=extents)
    return np.asarray(mesh.vertices) + np.asarray(center, float), np.asarray(mesh.faces)


def icosphere(subdivisions: int) -> tuple[FloatArray, IntArray]:
    """Build an outward-wound unit icosphere."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def sine_noise(directions: FloatArray, n_waves: int, seed: int) -> FloatArray:
    """Smooth noise on the unit sphere, a weighted sum of plane sine waves.

    Parameters
    ----------
    directions : ndarray, shape (n, 3)
        Unit vectors at which to evaluate the noise.
    n_waves : int
        Number of sine waves.
    seed : int
        Seed of the wave directions, frequencies, phases and weights.

    Returns
    -------
    ndarray, shape (n,)
        Noise values in [-1, 1].
    """
    rng = np.random.default_rng(seed)
    wave_dirs = unit(rng.normal(size=(n_waves, 3)))
    freqs = rng.uniform(2.0, 5.0, n_waves)
    phases = rng.uniform(0.0, 2.0 * np.pi, n_waves)
    weights = rng.uniform(0.5, 1.0, n_waves)
    weights /= weights.sum()
    return np.sin((directions @ wave_dirs.T) * freqs + phases) @ weights


def lumpy_sphere(radius: float, center: ArrayLike, amplitude: float,
                 seed: int) -> tuple[FloatArray, IntArray]:
    """Icosphere (subdivisions 6) with smooth radial displacement.

    The displacement is radial and keeps the radius positive, so the surface
    stays star-shaped, closed and outward-wound.
    """
    vertices, faces = icosphere(6)
    directions = unit(vertices)
    r = radius * (1.0 + amplitude * sine_noise(directions, n_waves=6, seed=seed))
    return directions * r[:, None] + np.asarray(center, float), faces


def rotation_matrix(axis: ArrayLike, degrees: float) -> FloatArray:
    """Right-handed rotation about ``axis`` by ``degrees`` (Rodrigues)."""
    a = unit(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * (k @ k)


def apply_transform(vertices: FloatArray, transform: dict[str, Any] | None) -> FloatArray:
    """Apply a scene transform: scale, then rotate, then translate."""
    if not transform:
        return vertices
    v = vertices * np.asarray(transform.get("scale", 1.0), dtype=np.float64)
    if "rotate" in transform:
        rot = transform["rotate"]
        v = v @ rotation_matrix(rot["axis"], rot["degrees"]).T
    return v + np.asarray(transform.get("translate", (0.0, 0.0, 0.0)), dtype=np.float64)


# ---------------------------------------------------------------------------
# The four scenes
# ---------------------------------------------------------------------------


def floor_quad(size: float = 6.0) -> tuple[FloatArray, IntArray]:
    """Square floor at z = 0 centred at the origin, front face up."""
    return quad((0, 0, 0), (size, 0, 0), (0, size, 0))


def down_light(center: ArrayLike, size_x: float, size_y: float) -> tuple[FloatArray, IntArray]:
    """Horizontal rectangular light whose front face points to -z."""
    return quad(center, (0, size_y, 0), (size_x, 0, 0))


def line_receivers(xs: ArrayLike, y: float = 0.0) -> ReceiverGroup:
    """Floor receivers at ``(x, y, 0)`` with normal +z."""
    points = np.array([[x, y, 0.0] for x in xs])
    return ReceiverGroup(points=points, normal=np.array([0.0, 0.0, 1.0]))


def occluded_quad() -> Scene:
    """Floor, a 1 x 0.5 light facing down and a thin box casting a shadow."""
    return Scene(
        name="occluded-quad",
        description="Floor lit by one rectangular light, a thin rotated box between them "
                    "casting umbra and penumbra.",
        files={"floor.obj": floor_quad(), "light.obj": down_light((0, 0, 2), 1.0, 0.5),
               "box.obj": box((1.0, 1.0, 1.0))},
        meshes=[MeshEntry("floor.obj"),
                MeshEntry("light.obj", emission=10.0),
                MeshEntry("box.obj", transform={
                    "translate": [0.3, 0.0, 1.0], "scale": [0.8, 1.0, 0.1],
                    "rotate": {"axis": [0.0, 0.0, 1.0], "degrees": 20.0}})],
        receivers=[line_receivers([-1.5, -0.6, -0.2, 0.3, 0.7, 1.3, 1.7, 2.4])],
        material={"type": "irradiance"},
    )


def two_lights() -> Scene:
    """Floor, a tiny bright light, a large dim tilted light and one occluder."""
    tilt = np.radians(20.0)
    large_u = 3.0 * np.array([0.0, 1.0, 0.0])
    large_v = 3.0 * np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    return Scene(
        name="two-lights",
        description="Floor under a tiny bright light (0.1 x 0.1, L = 2000) and a large dim "
                    "tilted one (3 x 3, L = 2); a small box shadows the tiny light.",
        files={"floor.obj": floor_quad(),
               "small_light.obj": down_light((0, 0, 1.5), 0.1, 0.1),
               "large_light.obj": quad((-0.5, 0, 2.5), large_u, large_v),
               "occluder.obj": box((0.2, 0.4, 0.05), center=(0.3, 0.0, 1.0))},
        meshes=[MeshEntry("floor.obj"),
                MeshEntry("small_light.obj", emission=2000.0),
                MeshEntry("large_light.obj", emission=2.0),
                MeshEntry("occluder.obj")],
        receivers=[line_receivers([-1.0, 0.0, 0.45, 0.6, 0.8, 1.0, 1.25, 1.6])],
        material={"type": "irradiance"},
    )


# The rest of Veach's geometry is common's; these are veach-plates' own (mitsuba-veach-plates has
# its own radii, mitsuba_scenes.VEACH_RADII).
VEACH_RADII = (0.03, 0.1, 0.3, 0.9)
VEACH_POWER = 0.81  # radius^2 * radiance, the same for every light: L = 900, 81, 9, 1
VEACH_EXPONENTS = (10.0, 50.0, 300.0, 2000.0)


def veach_plates() -> Scene:
    """Veach's multiple-importance-sampling test: four plates, four sphere lights."""
    files: dict[str, tuple[FloatArray, IntArray]] = {}
    meshes: list[MeshEntry] = []
    receivers: list[ReceiverGroup] = []
    for i, ((y, z), exponent) in enumerate(zip(VEACH_PLATES, VEACH_EXPONENTS), start=1):
        center = np.array([0.0, y, z])
        normal, vertices, faces = veach_plate(center)
        files[f"plate_{i}.obj"] = (vertices, faces)
        meshes.append(MeshEntry(f"plate_{i}.obj"))
        points = np.array([center + [x, 0.0, 0.0] for x in VEACH_LIGHT_X])
        material = {"type": "phong", "exponent": exponent, "albedo": 0.8,
                    "view": (VEACH_CAMERA - center).tolist()}
        receivers.append(ReceiverGroup(points, normal, name=f"plate-{i}", material=material))
    spheres = [SphereEntry(tuple((VEACH_LIGHT_ROW + [x, 0, 0]).tolist()), radius, VEACH_POWER / radius**2)
               for x, radius in zip(VEACH_LIGHT_X, VEACH_RADII)]
    return Scene(
        name="veach-plates",
        description="Veach's MIS scene: four phong plates of rising gloss and tilt reflecting "
                    "four analytic sphere lights with radius^2 * radiance constant.",
        files=files, meshes=meshes, receivers=receivers, spheres=spheres,
    )


def heavy_occluder() -> Scene:
    """Floor, a light facing down and an 81,920-triangle lumpy sphere between them."""
    return Scene(
        name="heavy-occluder",
        description="Floor lit by one rectangular light through a lumpy sphere of "
                    "81,920 triangles casting umbra and penumbra.",
        files={"floor.obj": floor_quad(),
               "light.obj": down_light((0, 0, 2.5), 0.6, 0.6),
               "occluder.ply": lumpy_sphere(0.45, (0.2, 0.0, 1.2), amplitude=0.25, seed=20240611)},
        meshes=[MeshEntry("floor.obj"),
                MeshEntry("light.obj", emission=10.0),
                MeshEntry("occluder.ply")],
        receivers=[line_receivers([-1.6, -0.9, -0.55, -0.2, 0.4, 0.9, 1.35, 2.0])],
        material={"type": "irradiance"},
    )


SCENE_BUILDERS = {
    "occluded-quad": occluded_quad,
    "two-lights": two_lights,
    "veach-plates": veach_plates,
    "heavy-occluder": heavy_occluder,
}


# ---------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------


def receivers_toml(groups: list[ReceiverGroup]) -> list[str]:
    """Format receiver groups as ``[receivers]`` or ``[[receivers]]`` tables."""
    single = len(groups) == 1 and groups[0].name is None and groups[0].material is None
    out = []
    for group in groups:
        out.append("[receivers]" if single else "[[receivers]]")
        if group.name is not None:
            out.append(f"name = {toml_value(group.name)}")
        out.append(toml_points(group.points))
        out.append(f"normal = {toml_value([float(c) for c in group.normal])}")
        if group.material is not None:
            out.append(f"material = {toml_value(group.material)}")
        out.append("")
    return out


def scene_toml(scene: Scene) -> str:
    """Render a scene as the text of its ``scene.toml``."""
    out = [f"name = {toml_value(scene.name)}",
           f"description = {toml_value(scene.description)}", ""]
    for entry in scene.meshes:
        out.append("[[mesh]]")
        out.append(f"path = {toml_value(entry.path)}")
        if entry.emission is not None:
            out.append(f"emission = {toml_value(float(entry.emission))}")
        if entry.transform is not None:
            out.append(f"transform = {toml_value(entry.transform)}")
        out.append("")
    for ball in scene.spheres:
        out.append("[[sphere]]")
        out.append(f"center = {toml_value([float(c) for c in ball.center])}")
        out.append(f"radius = {toml_value(float(ball.radius))}")
        if ball.emission is not None:
            out.append(f"emission = {toml_value(float(ball.emission))}")
        out.append("")
    out += receivers_toml(scene.receivers)
    if scene.material is not None:
        out += ["[material]"] + [f"{k} = {toml_value(v)}" for k, v in scene.material.items()]
    return "\n".join(out).rstrip("\n") + "\n"


def write_scene(scene: Scene, root: Path) -> Path:
    """Replace ``root/<scene.name>/`` by the scene file and its meshes."""
    folder = root / scene.name
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for file_name, (vertices, faces) in scene.files.items():
        write_mesh(folder / file_name, vertices, faces)
    (folder / "scene.toml").write_text(scene_toml(scene), encoding="utf-8", newline="\n")
    return folder


# ---------------------------------------------------------------------------
# Reading a scene back for verification
# ---------------------------------------------------------------------------


@dataclass
class LoadedScene:
    """A scene read back from disk, all meshes merged in world space.

    Attributes
    ----------
    name : str
        Scene name.
    mesh : trimesh.Trimesh
        All meshes concatenated, transforms applied.
    parts : list of trimesh.Trimesh
        The meshes one by one, transforms applied.
    mesh_of_face : ndarray, shape (n_faces,)
        Index into ``parts`` of every face of ``mesh``.
    emission : list of float or None
        Emission of every part.
    groups : list of dict
        Receiver groups: ``name``, ``points``, ``normals``, ``material``.
    """

    name: str
    mesh: trimesh.Trimesh
    parts: list[trimesh.Trimesh]
    mesh_of_face: IntArray
    emission: list[float | None]
    groups: list[dict[str, Any]] = field(default_factory=list)

    @property
    def emitters(self) -> list[int]:
        """Indices of the emitting parts."""
        return [i for i, e in enumerate(self.emission) if e]


def load_part(folder: Path, entry: dict[str, Any]) -> trimesh.Trimesh:
    """Load one ``[[mesh]]`` entry with trimesh and apply its transform."""
    raw = trimesh.load(folder / entry["path"], force="mesh", process=False)
    vertices = apply_transform(np.asarray(raw.vertices, dtype=np.float64), entry.get("transform"))
    return trimesh.Trimesh(vertices=vertices, faces=np.asarray(raw.faces), process=False)


def load_groups(data: dict[str, Any]) -> list[dict[str, Any]]:
    """Read receiver groups (explicit points only) from parsed TOML."""
    raw = data["receivers"]
    groups = [raw] if isinstance(raw, dict) else raw
    out = []
    for i, g in enumerate(groups):
        points = np.asarray(g["points"], dtype=np.float64)
        normals = np.asarray(g["normals"] if "normals" in g else [g["normal"]] * len(points))
        out.append({"name": g.get("name", f"group-{i + 1}"), "points": points,
                    "normals": unit(normals), "material": g.get("material", data.get("material"))})
    return out


def load_scene(name: str, root: Path) -> LoadedScene:
    """Read ``root/<name>/scene.toml`` and its meshes."""
    folder = root / name
    data = tomllib.loads((folder / "scene.toml").read_text(encoding="utf-8"))
    parts = [load_part(folder, entry) for entry in data["mesh"]]
    # Analytic spheres, as fine icospheres (5,120 triangles): the checks are ray casts and
    # visible fractions, for which that is close enough.
    for entry in data.get("sphere", []):
        vertices, faces = icosphere(4)
        parts.append(trimesh.Trimesh(vertices=np.asarray(entry["center"]) + entry["radius"] * vertices, faces=faces,
                                     process=False))
    mesh_of_face = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
    return LoadedScene(name=data["name"], mesh=trimesh.util.concatenate(parts), parts=parts,
                       mesh_of_face=mesh_of_face,
                       emission=[entry.get("emission") for entry in data["mesh"] + data.get("sphere", [])],
                       groups=load_groups(data))


# ---------------------------------------------------------------------------
# Verification
# ---------------------------------------------------------------------------


def make_intersector(mesh: trimesh.Trimesh) -> Any:
    """Embree ray intersector when available, else trimesh's default one.

    Raises
    ------
    RuntimeError
        If neither ``embreex`` nor ``rtree`` (needed by trimesh's default
        intersector) can be imported.
    """
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError:
        from trimesh.ray.ray_triangle import RayMeshIntersector
        try:
            import rtree  # noqa: F401
        except ImportError as exc:
            raise RuntimeError("verification needs embreex or rtree for trimesh ray casting; "
                               "pip install embreex") from exc
    return RayMeshIntersector(mesh)


def sample_surface(part: trimesh.Trimesh, n: int, seed: int) -> FloatArray:
    """Area-uniform points on a mesh with a fixed seed."""
    rng = np.random.default_rng(seed)
    tri = part.triangles
    face = rng.choice(len(tri), size=n, p=part.area_faces / part.area)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def visible_fraction(scene: LoadedScene, intersector: Any, point: FloatArray, normal: FloatArray,
                     emitter: int, samples: FloatArray) -> float | None:
    """Fraction of emitter samples seen from a receiver, None if all below horizon.

    A sample counts as visible when it lies above the receiver's tangent plane
    and the first hit along the ray towards it is a triangle of that emitter
    whose front face faces the receiver.
    """
    origin = point + RAY_OFFSET_ABSOLUTE * normal
    d = samples - origin
    above = d @ normal > 0.0
    if not above.any():
        return None
    dirs = unit(d[above])
    hit = intersector.intersects_first(np.repeat(origin[None], len(dirs), axis=0), dirs)
    found = hit >= 0
    h = hit[found]
    front = (scene.mesh.face_normals[h] * dirs[found]).sum(1) < 0.0
    ok = (scene.mesh_of_face[h] == emitter) & front
    return float(ok.sum()) / len(samples)


def check_meshes(scene: LoadedScene) -> None:
    """Assert consistent winding and outward orientation of closed meshes."""
    for i, part in enumerate(scene.parts):
        assert part.is_winding_consistent, f"{scene.name}: mesh {i} has inconsistent winding"
        if part.is_watertight:
            assert part.volume > 0, f"{scene.name}: closed mesh {i} is wound inwards"


def check_emitter_facing(scene: LoadedScene, points: FloatArray) -> None:
    """Assert every emitter shows its front to every receiver.

    Flat emitters must face each receiver with all their triangles, curved
    ones with at least one.
    """
    for e in scene.emitters:
        part = scene.parts[e]
        to_recv = points[:, None, :] - part.triangles_center[None, :, :]
        facing = (to_recv * part.face_normals[None]).sum(-1) > 0
        flat = np.allclose(part.face_normals, part.face_normals[0], atol=1e-6)
        ok = facing.all(axis=1) if flat else facing.any(axis=1)
        assert ok.all(), f"{scene.name}: emitter {e} turns its back on some receivers"


def check_on_surface(scene: LoadedScene, intersector: Any, points: FloatArray,
                     normals: FloatArray) -> None:
    """Assert every receiver lies on the front face of a surface."""
    origins = points + SURFACE_PROBE_ABSOLUTE * normals
    hit = intersector.intersects_first(origins, -normals)
    assert (hit >= 0).all(), f"{scene.name}: a receiver lies on no surface"
    fn = scene.mesh.face_normals[hit]
    offset = ((points - scene.mesh.triangles[hit][:, 0]) * fn).sum(1)
    assert np.abs(offset).max() < SURFACE_TOLERANCE_ABSOLUTE, f"{scene.name}: a receiver is off its surface"
    aligned = (fn * normals).sum(1) > 0.999
    assert aligned.all(), f"{scene.name}: a receiver normal is not its face's"


def print_counts(scene: LoadedScene, n_receivers: int) -> None:
    """Print triangle counts per mesh and per scene."""
    n_emit = sum(len(scene.parts[e].faces) for e in scene.emitters)
    print(f"\n== {scene.name}: {len(scene.mesh.faces)} triangles, {n_emit} emitter triangles, "
          f"{len(scene.emitters)} emitters, {n_receivers} receivers")
    for i, part in enumerate(scene.parts):
        emission = scene.emission[i]
        kind = f"emitter L={emission:g}" if emission else "surface"
        closed = "closed" if part.is_watertight else "open"
        print(f"   mesh {i}: {len(part.faces):6d} triangles, {closed}, {kind}")


def visibility_table(scene: LoadedScene, intersector: Any) -> list[list[str]]:
    """Print per-receiver visible fractions and return the labels."""
    samples = {e: sample_surface(scene.parts[e], MESH_VISIBILITY_SAMPLES, seed=1000 + e)
               for e in scene.emitters}
    header = "".join(f" | {f'mesh {e} (L={scene.emission[e]:g})':<19s}" for e in scene.emitters)
    print(f"   {'group':9s} {'#':>2s} {'point':>26s}{header}")
    labels = []
    for group in scene.groups:
        for j, (p, n) in enumerate(zip(group["points"], group["normals"])):
            fr = [visible_fraction(scene, intersector, p, n, e, samples[e]) for e in scene.emitters]
            labels.append([visibility_label(f) for f in fr])
            cells = "".join(f" | {'-' if f is None else f'{f:.3f}':>5s} {visibility_label(f):<13s}"
                            for f in fr)
            xyz = "(" + ", ".join(f"{c:6.2f}" for c in p) + ")"
            print(f"   {group['name']:9s} {j:2d} {xyz:>26s}{cells}")
    return labels


def print_mirror_angles(scene: LoadedScene, intersector: Any) -> None:
    """Print plate tilts and, per plate point, the mirrored view's angle to each light.

    Also asserts that every plate point sees the camera along its view
    direction and that its mirror direction hits the light above it.
    """
    centers = [scene.parts[e].bounds.mean(axis=0) for e in scene.emitters]
    for group in scene.groups:
        n, v = group["normals"][0], unit(group["material"]["view"])
        origins = group["points"] + RAY_OFFSET_ABSOLUTE * group["normals"]
        hidden = intersector.intersects_first(origins, np.repeat(v[None], len(origins), axis=0))
        assert (hidden < 0).all(), f"{scene.name}: {group['name']} is hidden from the camera"
        print(f"   {group['name']}: tilt {np.degrees(np.arccos(n[2])):5.2f} deg, "
              f"exponent {group['material']['exponent']:g}, seen from the camera")
    print("   mirror direction 2(n.v)n - v vs direction to each light centre (degrees):")
    for group in scene.groups:
        v = unit(group["material"]["view"])
        for j, (p, n) in enumerate(zip(group["points"], group["normals"])):
            mirror = 2.0 * (n @ v) * n - v
            angles = [np.degrees(np.arccos(np.clip(mirror @ unit(c - p), -1, 1))) for c in centers]
            cells = "  ".join(f"{a:6.2f}" for a in angles)
            print(f"   {group['name']} #{j} (exponent {group['material']['exponent']:g}): {cells}")
            assert angles[j] < 0.5, f"{scene.name}: mirror of point {j} misses light {j}"


def assert_shadow_mix(scene: LoadedScene, labels: list[list[str]]) -> None:
    """Assert lit, penumbra and umbra receivers w.r.t. the brightest emitter."""
    main = int(np.argmax([scene.emission[e] for e in scene.emitters]))
    seen = {row[main] for row in labels}
    missing = {"lit", "penumbra", "umbra"} - seen
    assert not missing, f"{scene.name}: no {sorted(missing)} receiver for emitter {main}"


def verify_scene(name: str, root: Path) -> list[list[str]]:
    """Read a written scene back and verify geometry and visibility.

    Parameters
    ----------
    name : str
        Scene name, the folder under ``root``.
    root : Path
        Folder holding the scene folders.

    Returns
    -------
    list of list of str
        Per receiver, the label for each emitter.
    """
    scene = load_scene(name, root)
    points = np.concatenate([g["points"] for g in scene.groups])
    normals = np.concatenate([g["normals"] for g in scene.groups])
    intersector = make_intersector(scene.mesh)
    print_counts(scene, len(points))
    check_meshes(scene)
    check_emitter_facing(scene, points)
    check_on_surface(scene, intersector, points, normals)
    labels = visibility_table(scene, intersector)
    if name == "veach-plates":
        print_mirror_angles(scene, intersector)
    else:
        assert_shadow_mix(scene, labels)
    if name == "heavy-occluder":
        assert len(scene.mesh.faces) >= 50_000, "heavy-occluder needs >= 50,000 triangles"
    return labels


# ---------------------------------------------------------------------------
# Writing every scene, checking the committed ones
# ---------------------------------------------------------------------------


def write_all(root: Path) -> None:
    """Write every scene under ``root``."""
    for name in SCENE_NAMES:
        write_scene(SCENE_BUILDERS[name](), root)


def generate(root: Path) -> None:
    """Write every scene under ``root`` and verify it (:func:`verify_scene`, which prints)."""
    for name in SCENE_NAMES:
        write_scene(SCENE_BUILDERS[name](), root)
        verify_scene(name, root)


def check(root: Path) -> int:
    """Regenerate every scene into a temporary folder and compare with ``root``; the exit status."""
    return check_tree(root, write_all, SCENE_NAMES)
