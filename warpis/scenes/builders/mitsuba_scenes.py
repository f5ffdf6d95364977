"""The Mitsuba 3 scenes bundled with warpis (``scripts/make_mitsuba_scenes.py``): their
builders, their writer and the verification of what was written.

Each scene folder holds a Mitsuba 3 ``scene.xml``, the PLY meshes it names and a
``scene.receivers.toml`` sidecar with warpis's receivers.  The builders are
deterministic (fixed float formatting, no timestamps), so the committed output can be
checked against a fresh run (:func:`check`).

After writing, every scene is read back by Mitsuba (``scalar_rgb``, the optional
``mitsuba`` package, imported inside the functions that need it) and verified
(:func:`verify_scene`): every receiver lies on a non-emitting surface (distance to the
nearest triangle below ``SURFACE_TOLERANCE_PER_DIAGONAL`` times the scene's bounding-box
diagonal, the normal given in the sidecar the surface's), the sensor sees the front of
that surface unoccluded, no surface coincides with an emitter, and the visible fraction
of each emitter from each receiver is printed.  On the plates, each point's mirror
direction must hit the light above it.  The scenes' sizes differ by three orders of
magnitude (metres, millimetres), so distances here are relative to the diagonal.

The scenes:

``mitsuba-veach-plates``
    Veach's multiple-importance-sampling scene (Veach 1997, fig. 9.2): the plates of
    ``veach-plates`` (:mod:`.mesh_scenes`) as Mitsuba ``roughconductor`` plates,
    four analytic sphere lights with radius² × radiance = 1.  The receivers are those of
    ``veach-plates`` moved along x to where the sensor, a point, sees each light's centre
    mirrored (``veach-plates`` views each plate from one direction).
``mitsuba-cornell-box``
    The Cornell box as measured by the Cornell Program of Computer Graphics (millimetres,
    y up), diffuse RGB reflectances, the ceiling light lowered 0.5 mm below the ceiling.
"""

from __future__ import annotations

import shutil
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .common import (VEACH_CAMERA, VEACH_LIGHT_ROW, VEACH_LIGHT_X, VEACH_PLATES, FloatArray, IntArray, check_tree,
                     clean, toml_points, toml_value, unit, veach_plate, visibility_label, write_ply)

SCENE_NAMES = ("mitsuba-veach-plates", "mitsuba-cornell-box")

# Distances relative to the scene's bounding-box diagonal (scene_diagonal), not absolute.
SURFACE_TOLERANCE_PER_DIAGONAL = 1e-6  # receiver to the nearest triangle
COINCIDENCE_TOLERANCE_PER_DIAGONAL = 1e-4  # emitter to any other surface
RAY_OFFSET_PER_DIAGONAL = 1e-4  # shadow and sensor rays start this far along the receiver's normal
MITSUBA_VISIBILITY_SAMPLES = 1000  # points on each emitter for a receiver's visible fraction


# ---------------------------------------------------------------------------
# Scene description
# ---------------------------------------------------------------------------


@dataclass
class Group:
    """One ``[[receivers]]`` group of the sidecar.

    Attributes
    ----------
    name : str
        Group name.
    points : ndarray, shape (n, 3) or None
        Receiver positions on a surface, or None for a grid.
    normal : ndarray, shape (3,) or None
        Normal to write, or None to leave the surface's geometric normal.
    grid : dict or None
        ``{shape, resolution}`` instead of points.
    """

    name: str
    points: FloatArray | None = None
    normal: FloatArray | None = None
    grid: dict[str, Any] | None = None


@dataclass
class MitsubaScene:
    """A scene to be written: mesh files, the XML text and the sidecar's receivers.

    Attributes
    ----------
    name : str
        Scene (and folder) name.
    description : str
        One-line description.
    files : dict of str to (vertices, faces)
        PLY meshes by file name, in world space.
    xml : str
        Text of ``scene.xml``.
    groups : list of Group
        Receiver groups.
    channel : str
        Colour channel warpis measures.
    expect_shadows : list of str
        Groups that must hold lit, penumbra and umbra receivers (w.r.t. every emitter).
    """

    name: str
    description: str
    files: dict[str, tuple[FloatArray, IntArray]]
    xml: str
    groups: list[Group]
    channel: str = "y"
    expect_shadows: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------
# XML text
# ---------------------------------------------------------------------------


def num(value: float) -> str:
    """A number as Mitsuba XML text: at most 6 decimals, no trailing zeros, no ``-0``."""
    return f"{float(clean(value)):.10g}"


def nums(values: ArrayLike) -> str:
    """Numbers as Mitsuba's comma-separated list."""
    return ", ".join(num(v) for v in np.ravel(values))


def rgb(name: str, value: ArrayLike) -> str:
    """An ``<rgb>`` property, one value when the three channels are equal."""
    v = np.ravel(np.asarray(value, dtype=np.float64))
    text = num(v[0]) if len(v) == 1 or np.all(v == v[0]) else nums(v)
    return f'<rgb name="{name}" value="{text}"/>'


def indent(lines: list[str], depth: int = 1) -> list[str]:
    """Lines indented by ``depth`` levels of four spaces."""
    return ["    " * depth + line if line else line for line in lines]


def element(tag: str, attrs: str, body: list[str]) -> list[str]:
    """An XML element with a body of lines, or self-closing without one."""
    if not body:
        return [f"<{tag} {attrs}/>"]
    return [f"<{tag} {attrs}>", *indent(body), f"</{tag}>"]


def diffuse(reflectance: ArrayLike, bsdf_id: str | None = None) -> list[str]:
    """A ``diffuse`` BSDF."""
    ident = "" if bsdf_id is None else f' id="{bsdf_id}"'
    return element("bsdf", f'type="diffuse"{ident}', [rgb("reflectance", reflectance)])


def ply_shape(shape_id: str, filename: str, bsdf: list[str]) -> list[str]:
    """A ``ply`` shape with flat (face) normals."""
    return element("shape", f'type="ply" id="{shape_id}"',
                   [f'<string name="filename" value="{filename}"/>',
                    '<boolean name="face_normals" value="true"/>', *bsdf])


def area_emitter(radiance: ArrayLike) -> list[str]:
    """An ``area`` emitter of the given radiance."""
    return element("emitter", 'type="area"', [rgb("radiance", radiance)])


def sensor(origin: ArrayLike, target: ArrayLike, up: ArrayLike, fov: float,
           width: str, height: str) -> list[str]:
    """A ``perspective`` sensor (horizontal ``fov``), its sampler and film."""
    return element("sensor", 'type="perspective" id="camera"', [
        f'<float name="fov" value="{num(fov)}"/>',
        '<string name="fov_axis" value="x"/>',
        *element("transform", 'name="to_world"',
                 [f'<lookat origin="{nums(origin)}" target="{nums(target)}" up="{nums(up)}"/>']),
        *element("sampler", 'type="independent"', ['<integer name="sample_count" value="$spp"/>']),
        *element("film", 'type="hdrfilm"', [f'<integer name="width" value="{width}"/>',
                                            f'<integer name="height" value="{height}"/>',
                                            '<rfilter type="box"/>']),
    ])


def direct_integrator() -> list[str]:
    """Mitsuba's ``direct`` integrator: one emitter and one BSDF sample, MIS-combined."""
    return element("integrator", 'type="direct"', ['<integer name="emitter_samples" value="$emitter_samples"/>',
                                                    '<integer name="bsdf_samples" value="$bsdf_samples"/>'])


def rectangle(shape_id: str, scale: ArrayLike, rotate: tuple[str, float] | None, translate: ArrayLike,
              bsdf: list[str]) -> list[str]:
    """A ``rectangle`` shape ([-1, 1]² in z = 0, normal +z): scale, rotate, translate."""
    ops = [f'<scale x="{num(scale[0])}" y="{num(scale[1])}"/>']
    if rotate is not None:
        ops.append(f'<rotate {rotate[0]}="1" angle="{num(rotate[1])}"/>')
    ops.append(f'<translate x="{num(translate[0])}" y="{num(translate[1])}" z="{num(translate[2])}"/>')
    return element("shape", f'type="rectangle" id="{shape_id}"', [*element("transform", 'name="to_world"', ops),
                                                                  *bsdf])


def scene_xml(comment: list[str], body: list[str]) -> str:
    """The text of a ``scene.xml``: header comment, then the scene element."""
    out = ['<?xml version="1.0" encoding="utf-8"?>', "", "<!--", *indent(comment), "-->", "",
           '<scene version="3.0.0">', *indent(body), "</scene>"]
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------


def as_stored(vertices: ArrayLike) -> FloatArray:
    """Vertices as a binary PLY stores them (rounded, then float32), back in float64."""
    return clean(vertices).astype(np.float32).astype(np.float64)


def quad_faces(vertices: FloatArray, inside: ArrayLike, outward: bool) -> IntArray:
    """The two triangles of a quad (fan from its first corner), wound so that their
    normal points away from (``outward``) or towards ``inside``."""
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    normal = np.cross(vertices[1] - vertices[0], vertices[2] - vertices[0])
    away = normal @ (vertices.mean(axis=0) - np.asarray(inside, float)) > 0
    return faces if away == outward else faces[:, ::-1]


def quads_mesh(quads: list[ArrayLike], inside: ArrayLike, outward: bool) -> tuple[FloatArray, IntArray]:
    """A mesh of quads, four vertices of its own each (flat faces), wound about ``inside``."""
    vertices, faces = [], []
    for i, q in enumerate(quads):
        q = np.asarray(q, dtype=np.float64)
        vertices.append(q)
        faces.append(quad_faces(q, inside, outward) + 4 * i)
    return np.vstack(vertices), np.vstack(faces)


def drop_onto(vertices: FloatArray, faces: IntArray, point: ArrayLike, axis: int) -> FloatArray:
    """The point of a mesh (as stored) on the line through ``point`` along ``axis``.

    Solves in float64 on the float32 vertices the PLY file holds, so that the result
    lies on the triangle the loader reads.

    Raises
    ------
    ValueError
        If the line meets no triangle.
    """
    p = np.asarray(point, dtype=np.float64)
    d = np.eye(3)[axis]
    for tri in as_stored(vertices)[faces]:
        e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
        h = np.cross(d, e2)
        det = e1 @ h
        if abs(det) < 1e-12:
            continue
        s = p - tri[0]
        u = (s @ h) / det
        q = np.cross(s, e1)
        v = (d @ q) / det
        if u >= 0 and v >= 0 and u + v <= 1:
            return p + ((e2 @ q) / det) * d
    raise ValueError(f"no triangle under {point} along axis {axis}")


# ---------------------------------------------------------------------------
# Veach's plates
# ---------------------------------------------------------------------------

# The rest of Veach's geometry is common's; these are mitsuba-veach-plates' own (not mesh_scenes.VEACH_RADII).
VEACH_RADII = (0.0333, 0.1, 0.3, 0.9)  # light radius; radiance 1/r^2: 901.803, 100, 11.1111, 1.23457
VEACH_ALPHAS = (0.3, 0.1, 0.04, 0.01)  # GGX roughness of plate-1 (nearest, roughest) … plate-4
# Mitsuba's "Al" conductor in RGB (its spectral data reduced by Mitsuba's scalar_rgb variant).
ALUMINIUM_ETA = (1.6575, 0.880405, 0.521244)
ALUMINIUM_K = (9.22381, 6.2695, 4.837)
VEACH_TARGET = (0.0, -1.5, 2.1)
VEACH_FOV = 44.0
VEACH_BACKDROP = 0.2


def mirror_xs(center: FloatArray, normal: FloatArray) -> list[float]:
    """x of the points of a plate where the sensor sees each light's centre mirrored.

    The plate's normal mirrors the camera onto the light row's centre through the
    plate's centre, and the plate contains the x axis, so the mirror point of the light
    at x_j is the centre moved along x by t x_j, t = d_C / (d_C + d_L), with d_C and
    d_L the camera's and the light row's distances to the plate's plane.
    """
    d_camera = (VEACH_CAMERA - center) @ normal
    d_light = (VEACH_LIGHT_ROW - center) @ normal
    t = d_camera / (d_camera + d_light)
    return [t * x for x in VEACH_LIGHT_X]


def veach_plates() -> MitsubaScene:
    """Veach's MIS scene: four roughconductor plates, four sphere lights, floor and backdrop."""
    files: dict[str, tuple[FloatArray, IntArray]] = {}
    groups: list[Group] = []
    body = ['<default name="spp" value="64"/>', '<default name="width" value="768"/>',
            '<default name="height" value="432"/>', '<default name="emitter_samples" value="1"/>',
            '<default name="bsdf_samples" value="1"/>', "",
            *direct_integrator(), "",
            *sensor(VEACH_CAMERA, VEACH_TARGET, (0, 0, 1), VEACH_FOV, "$width", "$height"), "",
            '<!-- The lights\' shells reflect nothing (Mitsuba\'s convention for emitters). -->',
            *diffuse(0.0, "light-shell"),
            *diffuse(VEACH_BACKDROP, "matte"), ""]
    body.append("<!-- Plates, nearest the camera first: rising tilt, falling roughness. -->")
    for i, ((y, z), alpha) in enumerate(zip(VEACH_PLATES, VEACH_ALPHAS), start=1):
        center = np.array([0.0, y, z])
        normal, vertices, faces = veach_plate(center)
        files[f"plate_{i}.ply"] = (vertices, faces)
        conductor = element("bsdf", 'type="roughconductor"', [
            '<string name="distribution" value="ggx"/>', f'<float name="alpha" value="{num(alpha)}"/>',
            rgb("eta", ALUMINIUM_ETA), rgb("k", ALUMINIUM_K)])
        body += element("shape", f'type="ply" id="plate-{i}"',
                        [f'<string name="filename" value="plate_{i}.ply"/>', *conductor])
        points = np.array([center + [x, 0.0, 0.0] for x in mirror_xs(center, normal)])
        groups.append(Group(f"plate-{i}", points=points, normal=normal))
    body += ["", "<!-- Sphere lights, radius^2 x radiance = 1: the smallest is the brightest. -->"]
    for i, (x, radius) in enumerate(zip(VEACH_LIGHT_X, VEACH_RADII), start=1):
        center = VEACH_LIGHT_ROW + [x, 0.0, 0.0]
        body += element("shape", f'type="sphere" id="light-{i}"', [
            f'<point name="center" x="{num(center[0])}" y="{num(center[1])}" z="{num(center[2])}"/>',
            f'<float name="radius" value="{num(radius)}"/>', '<ref id="light-shell"/>',
            *area_emitter(float(f"{1.0 / radius**2:.6g}"))])
    body += ["", "<!-- A floor under the plates and a backdrop behind the lights. -->",
             *rectangle("floor", (12, 12), None, (0, -3, 0), ['<ref id="matte"/>']),
             *rectangle("backdrop", (12, 8), ("x", 90), (0, 4, 8), ['<ref id="matte"/>'])]
    comment = [
        "Veach's multiple importance sampling scene (Veach 1997, fig. 9.2), written for warpis.",
        "Four aluminium roughconductor plates (GGX, alpha 0.3, 0.1, 0.04, 0.01 from the nearest",
        "plate to the farthest), each tilted to mirror the camera onto the row of lights; four",
        "sphere lights of radius 0.0333, 0.1, 0.3, 0.9 with radiance 1 / radius^2, so that every",
        "light has the same power. The geometry is that of warpis's veach-plates scene;",
        "scripts/make_mitsuba_scenes.py writes this file, its meshes and scene.receivers.toml.",
    ]
    return MitsubaScene(
        name="mitsuba-veach-plates",
        description="Veach's MIS scene in Mitsuba 3 XML: four aluminium roughconductor plates (GGX, alpha 0.3 "
                    "to 0.01) under four sphere lights with radius^2 * radiance constant.",
        files=files, xml=scene_xml(comment, body), groups=groups)


# ---------------------------------------------------------------------------
# The Cornell box
# ---------------------------------------------------------------------------

# The Cornell Program of Computer Graphics' measurements (millimetres; y up, the camera
# looking along +z; the red wall is at x ~ 550, on the camera's left).
CORNELL_FLOOR = [(552.8, 0, 0), (0, 0, 0), (0, 0, 559.2), (549.6, 0, 559.2)]
CORNELL_CEILING = [(556, 548.8, 0), (556, 548.8, 559.2), (0, 548.8, 559.2), (0, 548.8, 0)]
CORNELL_BACK = [(549.6, 0, 559.2), (0, 0, 559.2), (0, 548.8, 559.2), (556, 548.8, 559.2)]
CORNELL_RED = [(552.8, 0, 0), (549.6, 0, 559.2), (556, 548.8, 559.2), (556, 548.8, 0)]
# The green wall, (0, 0 .. 548.8, 0 .. 559.2), is an exact rectangle: a Mitsuba rectangle.
CORNELL_GREEN_SIZE = (548.8, 559.2)  # (height, depth)
CORNELL_SHORT_TOP = [(130, 165, 65), (82, 165, 225), (240, 165, 272), (290, 165, 114)]
CORNELL_TALL_TOP = [(423, 330, 247), (265, 330, 296), (314, 330, 456), (472, 330, 406)]
# The light, 130 x 105 at the ceiling's centre, lowered so that it does not touch it.
CORNELL_LIGHT_CENTER = (278.0, 548.3, 279.5)
CORNELL_LIGHT_HALF = (65.0, 52.5)  # half extents along x and z
CORNELL_CAMERA = (278.0, 273.0, -800.0)
CORNELL_FOV = 39.3077  # 2 atan(12.5 / 35): a 25 mm film at 35 mm focal length

CORNELL_WHITE = (0.725, 0.71, 0.68)
CORNELL_RED_RHO = (0.63, 0.065, 0.05)
CORNELL_GREEN_RHO = (0.14, 0.45, 0.091)
CORNELL_RADIANCE = (17.0, 12.0, 4.0)
CORNELL_ROOM_CENTER = (278.0, 274.4, 279.6)

# Receivers, projected onto their surface: (x, z) on the floor, (x, y) on the back wall,
# (y, z) on the red wall, (x, z) on the short box's top.
CORNELL_FLOOR_LIT = [(400.0, 150.0), (350.0, 40.0), (45.0, 380.0)]
CORNELL_FLOOR_PENUMBRA = [(500.0, 230.0), (230.0, 20.0)]
CORNELL_FLOOR_UMBRA = [(500.0, 400.0), (470.0, 320.0)]
CORNELL_BACK_POINTS = [(100.0, 300.0), (278.0, 450.0), (200.0, 180.0), (520.0, 130.0)]
CORNELL_RED_POINTS = [(100.0, 60.0), (400.0, 250.0), (150.0, 300.0), (60.0, 420.0)]
CORNELL_SHORT_POINTS = [(186.0, 169.0), (120.0, 110.0), (240.0, 240.0)]
CORNELL_GREEN_GRID = (4, 3)


def block(top: list[tuple[float, float, float]]) -> tuple[FloatArray, IntArray]:
    """A block of the Cornell box: its top quad and four vertical sides down to y = 0."""
    t = np.asarray(top, dtype=np.float64)
    b = t * [1.0, 0.0, 1.0]
    sides = [[b[i], b[(i + 1) % 4], t[(i + 1) % 4], t[i]] for i in range(4)]
    return quads_mesh([t, *sides], inside=t.mean(axis=0) * [1.0, 0.5, 1.0], outward=True)


def cornell_box() -> MitsubaScene:
    """The Cornell box: five walls, two blocks and a rectangular ceiling light."""
    room = CORNELL_ROOM_CENTER
    files = {
        "floor.ply": quads_mesh([CORNELL_FLOOR], room, outward=False),
        "ceiling.ply": quads_mesh([CORNELL_CEILING], room, outward=False),
        "back_wall.ply": quads_mesh([CORNELL_BACK], room, outward=False),
        "red_wall.ply": quads_mesh([CORNELL_RED], room, outward=False),
        "short_block.ply": block(CORNELL_SHORT_TOP),
        "tall_block.ply": block(CORNELL_TALL_TOP),
    }
    h, d = CORNELL_GREEN_SIZE
    # Rectangle x → world -z, y → world +y, normal +x; exact entries, no trigonometry.
    green_matrix = [0, 0, 1, 0, 0, h / 2, 0, h / 2, -d / 2, 0, 0, d / 2, 0, 0, 0, 1]
    green = element("shape", 'type="rectangle" id="green-wall"', [
        *element("transform", 'name="to_world"', [f'<matrix value="{" ".join(num(v) for v in green_matrix)}"/>']),
        '<ref id="green"/>'])
    light = rectangle("light", CORNELL_LIGHT_HALF, ("x", 90), CORNELL_LIGHT_CENTER,
                      ['<ref id="black"/>', *area_emitter(CORNELL_RADIANCE)])
    body = ['<default name="spp" value="64"/>', '<default name="resolution" value="512"/>',
            '<default name="emitter_samples" value="1"/>', '<default name="bsdf_samples" value="1"/>', "",
            *direct_integrator(), "",
            *sensor(CORNELL_CAMERA, np.add(CORNELL_CAMERA, (0, 0, 1)), (0, 1, 0), CORNELL_FOV,
                    "$resolution", "$resolution"), "",
            *diffuse(CORNELL_WHITE, "white"), *diffuse(CORNELL_RED_RHO, "red"),
            *diffuse(CORNELL_GREEN_RHO, "green"), *diffuse(0.0, "black"), "",
            *ply_shape("floor", "floor.ply", ['<ref id="white"/>']),
            *ply_shape("ceiling", "ceiling.ply", ['<ref id="white"/>']),
            *ply_shape("back-wall", "back_wall.ply", ['<ref id="white"/>']),
            *ply_shape("red-wall", "red_wall.ply", ['<ref name="bsdf" id="red"/>']),
            *green,
            *ply_shape("short-block", "short_block.ply", ['<ref id="white"/>']),
            *ply_shape("tall-block", "tall_block.ply", ['<ref id="white"/>']), "",
            "<!-- 130 x 105, 0.5 mm below the ceiling, facing down. -->",
            *light]
    comment = [
        "The Cornell box, written for warpis from the Cornell Program of Computer Graphics'",
        "measurements (millimetres, y up): floor, ceiling, back wall, red left wall, green right",
        "wall, a short and a tall block, and the 130 x 105 ceiling light, lowered 0.5 mm so that it",
        "does not coincide with the ceiling. Diffuse RGB reflectances; the camera of the",
        "measurements (35 mm lens, 25 mm film). scripts/make_mitsuba_scenes.py writes this file,",
        "its meshes and scene.receivers.toml.",
    ]

    def on(file: str, coords: list[tuple[float, float]], axis: int) -> FloatArray:
        vertices, faces = files[file]
        out = []
        for a, b in coords:
            guess = np.insert(np.array([a, b]), axis, 0.0)
            out.append(drop_onto(vertices, faces, guess, axis))
        return np.array(out)

    groups = [
        Group("floor", points=on("floor.ply", CORNELL_FLOOR_LIT + CORNELL_FLOOR_PENUMBRA + CORNELL_FLOOR_UMBRA, 1)),
        Group("back-wall", points=on("back_wall.ply", CORNELL_BACK_POINTS, 2)),
        Group("red-wall", points=on("red_wall.ply", CORNELL_RED_POINTS, 0)),
        Group("short-block-top", points=on("short_block.ply", CORNELL_SHORT_POINTS, 1)),
        Group("green-wall", grid={"shape": "green-wall", "resolution": list(CORNELL_GREEN_GRID)}),
    ]
    return MitsubaScene(
        name="mitsuba-cornell-box",
        description="The Cornell box in Mitsuba 3 XML: diffuse walls and blocks under a rectangular ceiling "
                    "light; floor receivers lit, in penumbra and in the tall block's umbra.",
        files=files, xml=scene_xml(comment, body), groups=groups, expect_shadows=["floor"])


SCENE_BUILDERS = {
    "mitsuba-veach-plates": veach_plates,
    "mitsuba-cornell-box": cornell_box,
}


# ---------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------


def receivers_toml(scene: MitsubaScene) -> str:
    """Render the sidecar ``scene.receivers.toml``."""
    out = [f"name = {toml_value(scene.name)}", f"description = {toml_value(scene.description)}",
           f"channel = {toml_value(scene.channel)}", ""]
    for group in scene.groups:
        out += ["[[receivers]]", f"name = {toml_value(group.name)}"]
        if group.grid is not None:
            out.append(f"grid = {toml_value(group.grid)}")
        else:
            out.append(toml_points(group.points))
        if group.normal is not None:
            out.append(f"normal = {toml_value([float(c) for c in group.normal])}")
        out.append("")
    return "\n".join(out).rstrip("\n") + "\n"


def write_scene(scene: MitsubaScene, root: Path) -> Path:
    """Replace ``root/<scene.name>/`` by the scene's XML, meshes and sidecar."""
    folder = root / scene.name
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for file_name, (vertices, faces) in scene.files.items():
        write_ply(folder / file_name, vertices, faces)
    (folder / "scene.xml").write_text(scene.xml, encoding="utf-8", newline="\n")
    (folder / "scene.receivers.toml").write_text(receivers_toml(scene), encoding="utf-8", newline="\n")
    return folder


# ---------------------------------------------------------------------------
# Reading a scene back with Mitsuba for verification
# ---------------------------------------------------------------------------


@dataclass
class Surface:
    """One shape of a scene as Mitsuba reads it, in world space.

    Attributes
    ----------
    id : str
        The shape's id.
    triangles : ndarray, shape (n, 3, 3) or None
        Triangles of a mesh or rectangle; None for a sphere.
    sphere : tuple of (ndarray, float) or None
        Centre and radius of a sphere.
    emitter : bool
        Whether the shape emits.
    rectangle : tuple of ndarray or None
        Centre and full edge vectors (u, v) of a rectangle.
    """

    id: str
    triangles: FloatArray | None
    sphere: tuple[FloatArray, float] | None
    emitter: bool
    rectangle: tuple[FloatArray, FloatArray, FloatArray] | None = None


def read_back(folder: Path) -> tuple[Any, list[Surface], FloatArray]:
    """Load ``folder/scene.xml`` with Mitsuba; its surfaces and the sensor's position."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    scene = mi.load_file(str(folder / "scene.xml"), optimize=False)  # keep shapes apart, ids and all
    surfaces = []
    for shape in scene.shapes():
        params = mi.traverse(shape)
        emitter = shape.emitter() is not None
        kind = shape.class_name()
        if kind not in ("Sphere", "Rectangle"):
            v = np.array(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
            f = np.array(params["faces"], dtype=np.int64).reshape(-1, 3)
            surfaces.append(Surface(shape.id(), v[f], None, emitter))
            continue
        m = np.array(params["to_world"].matrix, dtype=np.float64)
        c = m[:3, 3]
        if kind == "Sphere":
            surfaces.append(Surface(shape.id(), None, (c, float(np.linalg.norm(m[:3, 0]))), emitter))
            continue
        u, v = 2.0 * m[:3, 0], 2.0 * m[:3, 1]
        corners = np.array([c - u / 2 - v / 2, c + u / 2 - v / 2, c + u / 2 + v / 2, c - u / 2 + v / 2])
        surfaces.append(Surface(shape.id(), corners[[[0, 1, 2], [0, 2, 3]]], None, emitter, (c, u, v)))
    origin = np.array(scene.sensors()[0].world_transform().translation(), dtype=np.float64)
    return scene, surfaces, origin


def closest_on_triangles(triangles: FloatArray, p: FloatArray) -> tuple[float, int]:
    """Distance from ``p`` to the nearest of ``triangles`` and that triangle's index."""
    import trimesh

    closest = trimesh.triangles.closest_point(triangles, np.repeat(p[None], len(triangles), axis=0))
    d = np.linalg.norm(closest - p, axis=1)
    i = int(np.argmin(d))
    return float(d[i]), i


def triangle_normal(tri: FloatArray) -> FloatArray:
    """Unit geometric normal of a triangle (its winding's front)."""
    return unit(np.cross(tri[1] - tri[0], tri[2] - tri[0]))


def grid_points(surface: Surface, resolution: list[int]) -> FloatArray:
    """Cell centres of a ``resolution`` grid over a rectangle."""
    c, u, v = surface.rectangle
    nu, nv = resolution
    return np.array([c + ((i + 0.5) / nu - 0.5) * u + ((j + 0.5) / nv - 0.5) * v
                     for j in range(nv) for i in range(nu)])


def scene_diagonal(surfaces: list[Surface]) -> float:
    """Length of the diagonal of the bounding box of every surface."""
    pts = [s.triangles.reshape(-1, 3) for s in surfaces if s.triangles is not None]
    pts += [np.array([s.sphere[0] - s.sphere[1], s.sphere[0] + s.sphere[1]]) for s in surfaces if s.sphere]
    allp = np.vstack(pts)
    return float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))


def emitter_samples(surface: Surface, n: int, seed: int) -> tuple[FloatArray, FloatArray]:
    """Area-uniform points on an emitter and their outward (front) normals."""
    rng = np.random.default_rng(seed)
    if surface.sphere is not None:
        c, r = surface.sphere
        d = unit(rng.normal(size=(n, 3)))
        return c + r * d, d
    c, u, v = surface.rectangle
    a, b = rng.random(n) - 0.5, rng.random(n) - 0.5
    return c + a[:, None] * u + b[:, None] * v, np.repeat(unit(np.cross(u, v))[None], n, axis=0)


def visible_fraction(scene: Any, p: FloatArray, n: FloatArray, points: FloatArray, normals: FloatArray,
                     offset: float) -> float | None:
    """Fraction of the emitter samples facing ``p`` that lie above its horizon and are
    unoccluded; None when the whole emitter is below the horizon."""
    import mitsuba as mi

    origin = p + offset * n
    d = points - origin
    dist = np.linalg.norm(d, axis=1)
    d = d / dist[:, None]
    above = d @ n > 0
    if not above.any():
        return None
    facing = (normals * d).sum(axis=1) < 0
    seen = 0
    for k in np.flatnonzero(above & facing):
        ray = mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*d[k]))
        ray.maxt = float(dist[k] * (1.0 - 1e-4))
        seen += not scene.ray_test(ray)
    return seen / max(1, int(facing.sum()))


def verify_scene(name: str, root: Path) -> None:
    """Read a written scene back with Mitsuba and verify its receivers and emitters.

    Raises
    ------
    AssertionError
        On a receiver off its surface, on an emitter's back or hidden from the
        sensor, an emitter touching another surface, or a missing shadow class.
    """
    import mitsuba as mi

    folder = root / name
    scene, surfaces, sensor_at = read_back(folder)
    sidecar = tomllib.loads((folder / "scene.receivers.toml").read_text(encoding="utf-8"))
    diag = scene_diagonal(surfaces)
    by_id = {s.id: s for s in surfaces}
    solid = [s for s in surfaces if not s.emitter and s.triangles is not None]
    emitters = [s for s in surfaces if s.emitter]
    n_tri = sum(len(s.triangles) for s in solid)
    print(f"\n== {name}: {len(surfaces)} shapes ({n_tri} triangles besides the emitters), "
          f"{len(emitters)} emitters, sensor at {np.round(sensor_at, 4).tolist()}")

    for e in emitters:  # no other surface within the tolerance of an emitter's samples
        pts, _ = emitter_samples(e, 200, seed=7)
        gap = min(closest_on_triangles(s.triangles, p)[0] for s in solid for p in pts)
        assert gap > COINCIDENCE_TOLERANCE_PER_DIAGONAL * diag, \
            f"{name}: emitter {e.id} touches another surface ({gap:g})"
        print(f"   emitter {e.id}: nearest other surface {gap:.4g} away")

    samples = {e.id: emitter_samples(e, MITSUBA_VISIBILITY_SAMPLES, seed=1000 + i) for i, e in enumerate(emitters)}
    header = "".join(f" | {e.id:<22s}" for e in emitters)
    print(f"   {'group':16s} {'#':>2s} {'point':>30s} {'on':>12s}{header}")
    labels: dict[str, list[list[str]]] = {}
    worst = 0.0
    for group in sidecar["receivers"]:
        if "grid" in group:
            points = grid_points(by_id[group["grid"]["shape"]], group["grid"]["resolution"])
        else:
            points = np.asarray(group["points"], dtype=np.float64)
        labels[group["name"]] = []
        for j, p in enumerate(points):
            found = [(closest_on_triangles(s.triangles, p), s) for s in solid]
            (dist, tri), surface = min(found, key=lambda t: t[0][0])
            assert dist < SURFACE_TOLERANCE_PER_DIAGONAL * diag, \
                f"{name}: {group['name']} #{j} is {dist:g} off any surface"
            worst = max(worst, dist / diag)
            normal = triangle_normal(surface.triangles[tri])
            if "normal" in group:
                assert unit(group["normal"]) @ normal > 1 - 1e-6, f"{name}: {group['name']} #{j}: normal differs"
            to_sensor = sensor_at - p
            assert to_sensor @ normal > 0, f"{name}: {group['name']} #{j}: the sensor sees its back"
            ray = mi.Ray3f(mi.Point3f(*(p + RAY_OFFSET_PER_DIAGONAL * diag * normal)), mi.Vector3f(*unit(to_sensor)))
            ray.maxt = float(np.linalg.norm(to_sensor))
            assert not scene.ray_test(ray), f"{name}: {group['name']} #{j} is hidden from the sensor"
            fr = [visible_fraction(scene, p, normal, *samples[e.id], RAY_OFFSET_PER_DIAGONAL * diag) for e in emitters]
            labels[group["name"]].append([visibility_label(f) for f in fr])
            cells = "".join(f" | {'-' if f is None else f'{f:.3f}':>5s} {visibility_label(f):<16s}" for f in fr)
            xyz = "(" + ", ".join(f"{c:8.2f}" for c in p) + ")"
            print(f"   {group['name']:16s} {j:2d} {xyz:>30s} {surface.id:>12s}{cells}")

    print(f"   receivers lie on their surfaces within {worst:.2g} of the scene's diagonal ({diag:.4g})")
    scene_def = SCENE_BUILDERS[name]()
    for g in scene_def.expect_shadows:
        seen = {row[k] for row in labels[g] for k in range(len(emitters))}
        missing = {"lit", "penumbra", "umbra"} - seen
        assert not missing, f"{name}: group {g} has no {sorted(missing)} receiver"
    if name == "mitsuba-veach-plates":
        check_mirrors(sidecar, sensor_at, emitters)


def check_mirrors(sidecar: dict[str, Any], sensor_at: FloatArray, emitters: list[Surface]) -> None:
    """Assert that each plate point mirrors the sensor onto the light above it."""
    centres = [e.sphere[0] for e in emitters]
    print("   mirror direction vs direction to each light centre (degrees):")
    for group in sidecar["receivers"]:
        n = unit(group["normal"])
        for j, p in enumerate(np.asarray(group["points"], dtype=np.float64)):
            v = unit(sensor_at - p)
            mirror = 2.0 * (n @ v) * n - v
            angles = [np.degrees(np.arccos(np.clip(mirror @ unit(c - p), -1, 1))) for c in centres]
            print(f"   {group['name']} #{j}: " + "  ".join(f"{a:6.2f}" for a in angles))
            assert angles[j] < 0.5, f"{group['name']} #{j}: its mirror direction misses light {j + 1}"


def render_preview(name: str, out: Path, root: Path, spp: int = 16) -> Path:
    """Render a small preview of a scene with Mitsuba into ``out/<name>.png``."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    scene = mi.load_file(str(root / name / "scene.xml"), spp=spp)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.png"
    mi.util.write_bitmap(str(path), mi.render(scene, spp=spp))
    return path


# ---------------------------------------------------------------------------
# Writing every scene, checking the committed ones
# ---------------------------------------------------------------------------


def write_all(root: Path) -> None:
    """Write every scene under ``root``."""
    for name in SCENE_NAMES:
        write_scene(SCENE_BUILDERS[name](), root)


def generate(root: Path, preview: Path | None = None) -> None:
    """Write every scene under ``root`` and verify it (:func:`verify_scene`, which prints);
    with ``preview``, also render each into that folder (:func:`render_preview`)."""
    for name in SCENE_NAMES:
        write_scene(SCENE_BUILDERS[name](), root)
        verify_scene(name, root)
        if preview is not None:
            print(f"   preview: {render_preview(name, preview, root)}")


def check(root: Path) -> int:
    """Regenerate every scene into a temporary folder and compare with ``root``; the exit status."""
    return check_tree(root, write_all, SCENE_NAMES)
