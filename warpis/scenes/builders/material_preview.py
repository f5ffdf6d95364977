"""The bundled ``mitsuba-material-preview`` scene (``scripts/make_material_preview.py``).

In the spirit of Mitsuba's material-preview scene, every piece made here: a procedural
HDR sky (a blue gradient over a dim ground and a small sun, 128 × 64 texels, written as
a PFM with numpy, rotated by the envmap's to_world), a checkerboard-textured diffuse
floor, and two glossy spheres on one smooth-normal mesh (an icosphere with its vertex
normals, so that Mitsuba and warpis shade with the interpolated normals): a gold
``roughconductor`` of alpha 0.08 and a blue ``roughplastic`` of alpha 0.3.  A
perspective camera looks at them.

The receivers (``scene.receivers.toml``) are where the camera's rays through a fixed
grid of pixels first meet each surface, 12 on each sphere and 12 on the floor, away
from grazing angles and from the spheres' contact shadows: finding them needs the
optional ``mitsuba`` package, imported inside :func:`receivers`.  Deterministic: the
same files on every run (:func:`check` compares them with the committed ones).
"""

from __future__ import annotations

import filecmp
import tempfile
from pathlib import Path

import numpy as np
import trimesh

NAME = "mitsuba-material-preview"
SKY = (128, 64)  # width, height
CAMERA = ((0.0, 1.3, 3.6), (0.0, 0.45, 0.0))  # origin, target
FILM = (96, 64)
PER_SHAPE = 12

XML = """<?xml version="1.0" encoding="utf-8"?>

<!--
    warpis's material-preview scene: two glossy spheres (one smooth-normal icosphere mesh)
    on a checkerboard floor under a procedural HDR sky with a sun.
    scripts/make_material_preview.py writes this file, sky.pfm, sphere.ply and
    scene.receivers.toml.
-->

<scene version="3.0.0">
    <integrator type="direct"/>

    <sensor type="perspective" id="camera">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="{origin}" target="{target}" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
        </film>
    </sensor>

    <emitter type="envmap" id="sky">
        <string name="filename" value="sky.pfm"/>
        <transform name="to_world"><rotate y="1" angle="60"/></transform>
    </emitter>

    <shape type="rectangle" id="floor">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/></transform>
        <bsdf type="diffuse">
            <texture type="checkerboard" name="reflectance">
                <rgb name="color0" value="0.15, 0.2, 0.25"/>
                <rgb name="color1" value="0.6, 0.55, 0.5"/>
                <transform name="to_uv"><scale value="8"/></transform>
            </texture>
        </bsdf>
    </shape>

    <shape type="ply" id="gold">
        <string name="filename" value="sphere.ply"/>
        <transform name="to_world"><scale value="0.45"/><translate x="-0.55" y="0.45" z="0"/></transform>
        <bsdf type="roughconductor">
            <string name="material" value="Au"/>
            <string name="distribution" value="ggx"/>
            <float name="alpha" value="0.08"/>
        </bsdf>
    </shape>

    <shape type="ply" id="plastic">
        <string name="filename" value="sphere.ply"/>
        <transform name="to_world"><scale value="0.45"/><translate x="0.55" y="0.45" z="0"/></transform>
        <bsdf type="roughplastic">
            <string name="distribution" value="ggx"/>
            <float name="alpha" value="0.3"/>
            <rgb name="diffuse_reflectance" value="0.1, 0.25, 0.6"/>
        </bsdf>
    </shape>
</scene>
"""


def sky() -> np.ndarray:
    """(H, W, 3) float32 linear sRGB: zenith blue to a bright horizon, a dim brown ground,
    a 3 × 3-texel sun of 150 (warm) 35° from the zenith."""
    width, height = SKY
    theta = np.pi * (np.arange(height) + 0.5) / height
    up = np.cos(theta)[:, None, None]
    zenith, horizon, ground = np.array([0.25, 0.45, 0.9]), np.array([1.2, 1.25, 1.4]), np.array([0.1, 0.08, 0.06])
    t = np.clip(up, 0.0, 1.0) ** 0.5
    rgb = np.where(up > 0, horizon * (1 - t) + zenith * t, ground) * np.ones((height, width, 1))
    row, col = int(round(35 / 180 * height)), width // 6
    rgb[row - 1:row + 2, col - 1:col + 2] = 150.0 * np.array([1.0, 0.9, 0.75])
    return rgb.astype(np.float32)


def write_pfm(path: Path, rgb: np.ndarray) -> None:
    """A little-endian PFM (rows stored bottom to top), which Mitsuba's Bitmap reads."""
    height, width, _ = rgb.shape
    with open(path, "wb") as fh:
        fh.write(f"PF\n{width} {height}\n-1.0\n".encode())
        fh.write(np.ascontiguousarray(rgb[::-1], dtype="<f4").tobytes())


def write_sphere(path: Path) -> None:
    """A unit icosphere (1280 faces) with its vertex normals, as ASCII PLY."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x", "property float y",
             "property float z", "property float nx", "property float ny", "property float nz",
             f"element face {len(mesh.faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{x:.7g}" for x in (*p, *q)) for p, q in zip(v, n)]
    lines += [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def receivers(folder: Path) -> str:
    """The receivers file: camera hits on each shape, spread over a pixel grid."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    scene = mi.load_file(str(folder / "scene.xml"), parallel=False, optimize=False)
    sensor = scene.sensors()[0]
    origin = np.array(CAMERA[0])
    hits: dict[str, list[list[float]]] = {"gold": [], "plastic": [], "floor": []}
    spheres = {"gold": np.array([-0.55, 0.45, 0.0]), "plastic": np.array([0.55, 0.45, 0.0])}
    width, height = FILM
    for y in range(2, height, 3):
        for x in range(2, width, 3):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + 0.5) / width, (y + 0.5) / height), mi.Point2f(0.5))
            si = scene.ray_intersect(ray)
            if not si.is_valid():
                continue
            p = np.array(si.p, dtype=np.float64)
            view = (origin - p) / np.linalg.norm(origin - p)
            if float(np.dot(np.array(si.sh_frame.n), view)) < 0.3:
                continue  # grazing
            shape = si.shape.id()
            if shape == "floor" and min(np.linalg.norm(p - c) for c in spheres.values()) < 0.9:
                continue  # the spheres' contact shadows: Mitsuba's ray offsets would matter there
            hits[shape].append([float(c) for c in np.array(si.p, dtype=np.float32)])
    out = [f'name = "{NAME}"',
           'description = "Two glossy spheres (a gold roughconductor, alpha 0.08; a blue roughplastic, alpha 0.3) on '
           'one smooth-normal mesh, over a checkerboard floor, under a procedural HDR sky with a sun."',
           'channel = "y"', ""]
    for shape, points in hits.items():
        chosen = [points[i] for i in np.linspace(0, len(points) - 1, PER_SHAPE).round().astype(int)]
        out += ["[[receivers]]", f'name = "{shape}"', "points = ["]
        out += [f"    [{x!r}, {y!r}, {z!r}]," for x, y, z in chosen]
        out += ["]", ""]
    return "\n".join(out)


def write(folder: Path) -> None:
    """Write the scene's files into ``folder``: scene.xml, sky.pfm, sphere.ply, scene.receivers.toml."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.xml").write_text(XML.format(origin=", ".join(map(str, CAMERA[0])),
                                                 target=", ".join(map(str, CAMERA[1])), width=FILM[0],
                                                 height=FILM[1]))
    write_pfm(folder / "sky.pfm", sky())
    write_sphere(folder / "sphere.ply")
    (folder / "scene.receivers.toml").write_text(receivers(folder))


def check(target: Path) -> int:
    """Write the scene into a temporary folder and compare with ``target`` (the committed
    folder); prints the verdict and returns the exit status (1 if a file differs)."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp) / NAME
        write(fresh)
        names = sorted(p.name for p in fresh.iterdir())
        _, mismatch, errors = filecmp.cmpfiles(fresh, target, names, shallow=False)
        # The receivers are Mitsuba's ray hits, whose float32 rounding differs between
        # CPUs (its kernels use whatever FMA the machine has): the same points to
        # POINT_TOLERANCE are the same file.
        if "scene.receivers.toml" in mismatch and _same_points(fresh / "scene.receivers.toml",
                                                              target / "scene.receivers.toml"):
            mismatch.remove("scene.receivers.toml")
        if mismatch or errors:
            print(f"{target}: differs from a fresh run: {', '.join(mismatch + errors)}")
            return 1
    print(f"{target}: up to date")
    return 0


# A hit 4 units from the camera is a float32 o + t·d: one ulp of t there is 4.8e-7, and
# two CPUs' roundings were seen 1.01e-6 apart (an AVX-512 Xeon against the machine that
# wrote the files).  1e-5 allows ~20 such ulps; a point that really moved (another
# pixel, another shape) moves by a hundredth of a unit or more.
POINT_TOLERANCE = 1e-5


def _same_points(a: Path, b: Path, atol: float = POINT_TOLERANCE) -> bool:
    """Whether two receivers files are the same but for the points' last digits."""
    import tomllib

    da, db = tomllib.loads(a.read_text()), tomllib.loads(b.read_text())
    groups_a, groups_b = da.pop("receivers"), db.pop("receivers")
    if da != db or len(groups_a) != len(groups_b):
        return False
    for ga, gb in zip(groups_a, groups_b):
        pa, pb = np.array(ga.pop("points")), np.array(gb.pop("points"))
        if ga != gb or pa.shape != pb.shape or not np.allclose(pa, pb, rtol=0.0, atol=atol):
            return False
    return True
