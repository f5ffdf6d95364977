"""Shadow rays three ways: one at a time through warpis's 4-wide BVH (what warpis casts),
four at a time through the same tree, and one at a time through Embree, called from the
Warp kernel.

    python scripts/bench_shadow_rays.py [--scenes occluded-quad heavy-occluder] [--n 64]
                                        [--trials 2000] [--repeat 5]

Every side draws the same ``light-area`` samples (``sample_light_point``) at every
receiver of the scene and casts the same shadow rays as ``radiance_unless_blocked``: from
where the ray leaves the receiver's slab to where it enters the emitter's.

* *one at a time*: ``_any``, as ``any_hit_between`` calls it (hits on the receiver's and
  the emitter's planes ignored).
* *four together*: a trial's rays (one origin) traversed four at a time with one node
  stack, each entry carrying the bit mask of the rays that entered it; a node's boxes
  are tested for each of those rays (``_entries``), a leaf's triangles likewise
  (``_leaf_blocks``), and a ray leaves the packet when something blocks it.  Its visible
  counts must equal one at a time's exactly (the script stops otherwise).
* *Embree*: Embree 4's ``rtcOccluded1`` on a scene of the same float32 triangles (robust
  mode, watertight), called by address from the kernel (``wp.func_native``; Warp's CPU
  JIT calls any function pointer it is given).  Its own triangle arithmetic, without the
  ignored planes: the rays whose visibility differs from warpis's are counted and shown.
  Needs ``embreex`` (the ``bench`` extra), whose wheel bundles libembree4; left out, with
  a line saying why, where it is missing.

The rate is rays (samples) per second of one launch on one thread, the sampling included;
the sides alternate ``--repeat`` times, medians.  A benchmark of levers for the issue on
time to the first answer: the packet does not pay in Warp's scalar CPU code (it shares the
stack and the node loads, not the box and triangle tests); Embree, whose traversal is
vectorised within each ray, does.  It reads private functions of ``warpis.kernels.bvh``.
"""

from __future__ import annotations

import argparse
import ctypes
import glob
import os
import statistics
import time

import numpy as np
import warp as wp

import warpis
from warpis.kernels import bvh
from warpis.kernels.bvh import INFINITY, NodeStack, Planes, Ray, WideBvh
from warpis.kernels.device import ReceiverData, SceneData, upload
from warpis.kernels.integrand import shading_point
from warpis.kernels.rng import stream, uniform
from warpis.kernels.techniques import LIGHT_AREA, sample_light_point

MaskStack = wp.types.vector(length=64, dtype=wp.int32)


@wp.func
def lane_blocked(tree: WideBvh, leaf: wp.int32, r: Ray, t_max: float, planes: Planes) -> bool:
    """Whether a triangle of the leaf blocks the ray, hits on the ignored planes left out (as _wide_any)."""
    slot = bvh._leaf_blocks(tree, leaf, r, t_max, 0)
    skip = wp.int32(0)
    while slot >= 0 and bvh._leaf_ignores(tree, leaf, slot, planes):
        skip = skip | (1 << slot)
        slot = bvh._leaf_blocks(tree, leaf, r, t_max, skip)
    return slot >= 0


@wp.func
def entered(tree: WideBvh, node: wp.int32, r: Ray, t_max: float, bit: wp.int32, masks: wp.vec4i) -> wp.vec4i:
    """``masks`` with ``bit`` set for each child box of ``node`` the ray enters."""
    d = bvh._entries(tree, node, r, t_max)
    out = masks
    for i in range(4):
        if d[i] < INFINITY:
            out[i] = out[i] | bit
    return out


@wp.func
def blocked_of_four(tree: WideBvh, r0: Ray, r1: Ray, r2: Ray, r3: Ray, t_max: wp.vec4, p0: Planes, p1: Planes,
                    p2: Planes, p3: Planes, active: wp.int32) -> wp.int32:
    """The bit mask of the ``active`` rays that something blocks, the four traversed together."""
    nodes = NodeStack()
    masks = MaskStack()
    top = wp.int32(1)
    nodes[0] = 0
    masks[0] = active
    blocked = wp.int32(0)
    while top > 0:
        top -= 1
        node = nodes[top]
        m = masks[top] & ~blocked
        if m != 0:
            if node < 0:
                leaf = -node - 1
                if (m & 1) != 0 and lane_blocked(tree, leaf, r0, t_max[0], p0):
                    blocked = blocked | 1
                if (m & 2) != 0 and lane_blocked(tree, leaf, r1, t_max[1], p1):
                    blocked = blocked | 2
                if (m & 4) != 0 and lane_blocked(tree, leaf, r2, t_max[2], p2):
                    blocked = blocked | 4
                if (m & 8) != 0 and lane_blocked(tree, leaf, r3, t_max[3], p3):
                    blocked = blocked | 8
                if blocked == active:
                    return blocked
            else:
                child = wp.vec4i(0, 0, 0, 0)
                if (m & 1) != 0:
                    child = entered(tree, node, r0, t_max[0], 1, child)
                if (m & 2) != 0:
                    child = entered(tree, node, r1, t_max[1], 2, child)
                if (m & 4) != 0:
                    child = entered(tree, node, r2, t_max[2], 4, child)
                if (m & 8) != 0:
                    child = entered(tree, node, r3, t_max[3], 8, child)
                kids = tree.children[node]
                for i in range(4):
                    if child[i] != 0:
                        nodes[top] = kids[i]
                        masks[top] = child[i]
                        top += 1
    return blocked


@wp.func
def shadow_ray(scene: SceneData, p: wp.vec3, n: wp.vec3, ng: wp.vec3, slab: float, w: wp.vec3, k: wp.int32,
               t: float):
    """radiance_unless_blocked's shadow ray towards emitter k at distance t: (ray, planes, length)."""
    lead = slab / wp.max(wp.abs(wp.dot(ng, w)), 1.0e-12)
    cos_y = wp.abs(wp.dot(scene.emitter_normal[k], w))
    y = p + t * w
    y_slab = bvh.SELF_HIT * wp.max(wp.max(wp.abs(y[0]), wp.abs(y[1])), wp.abs(y[2]))
    tail = wp.max(scene.emitter_slab[k], y_slab) / wp.max(cos_y, 1.0e-12)
    return bvh.make_ray(p + lead * w, w), bvh._planes(p, n, y, scene.emitter_normal[k], 1), t - lead - tail


@wp.kernel
def packet_kernel(scene: SceneData, recv: ReceiverData, n: wp.int32, out: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    sp = shading_point(scene, recv, i)
    s = stream(wp.uint32(1), i, j, 0)
    visible = wp.int32(0)
    for group in range(n / 4):
        q = group * 4
        a0 = sample_light_point(LIGHT_AREA, scene, sp, wp.vec2(uniform(s, q, 0), uniform(s, q, 1)))
        a1 = sample_light_point(LIGHT_AREA, scene, sp, wp.vec2(uniform(s, q + 1, 0), uniform(s, q + 1, 1)))
        a2 = sample_light_point(LIGHT_AREA, scene, sp, wp.vec2(uniform(s, q + 2, 0), uniform(s, q + 2, 1)))
        a3 = sample_light_point(LIGHT_AREA, scene, sp, wp.vec2(uniform(s, q + 3, 0), uniform(s, q + 3, 1)))
        r0, p0, l0 = shadow_ray(scene, sp.p, sp.n, sp.ng, sp.slab, a0.w, a0.emitter, a0.t)
        r1, p1, l1 = shadow_ray(scene, sp.p, sp.n, sp.ng, sp.slab, a1.w, a1.emitter, a1.t)
        r2, p2, l2 = shadow_ray(scene, sp.p, sp.n, sp.ng, sp.slab, a2.w, a2.emitter, a2.t)
        r3, p3, l3 = shadow_ray(scene, sp.p, sp.n, sp.ng, sp.slab, a3.w, a3.emitter, a3.t)
        active = wp.int32(0)
        if wp.dot(sp.n, a0.w) > 0.0 and l0 > 0.0:
            active = active | 1
        if wp.dot(sp.n, a1.w) > 0.0 and l1 > 0.0:
            active = active | 2
        if wp.dot(sp.n, a2.w) > 0.0 and l2 > 0.0:
            active = active | 4
        if wp.dot(sp.n, a3.w) > 0.0 and l3 > 0.0:
            active = active | 8
        if active != 0:
            lit = active & ~blocked_of_four(scene.bvh, r0, r1, r2, r3, wp.vec4(l0, l1, l2, l3), p0, p1, p2, p3,
                                            active)
            visible += (lit & 1) + ((lit >> 1) & 1) + ((lit >> 2) & 1) + ((lit >> 3) & 1)
    out[i, j] = visible


# --------------------------------------------------------------------------- Embree, by address

EMBREE_OCCLUDED = """
struct alignas(16) EmbreeRay { float ox, oy, oz, tnear, dx, dy, dz, time, tfar; wp::uint32 mask, id, flags; };
typedef void (*occluded_t)(void*, EmbreeRay*, void*);
EmbreeRay r;
r.ox = o[0]; r.oy = o[1]; r.oz = o[2]; r.tnear = 0.0f;
r.dx = d[0]; r.dy = d[1]; r.dz = d[2]; r.time = 0.0f; r.tfar = t_max;
r.mask = 0xFFFFFFFFu; r.id = 0; r.flags = 0;
((occluded_t)fn)((void*)scn, &r, nullptr);
return r.tfar < 0.0f;
"""


@wp.func_native(EMBREE_OCCLUDED)
def embree_occluded(fn: wp.uint64, scn: wp.uint64, o: wp.vec3, d: wp.vec3, t_max: float) -> bool:
    """Embree's rtcOccluded1 (at address ``fn``) on scene ``scn``: something at 0 ≤ t ≤ t_max (tfar set to −inf)."""


@wp.kernel
def one_at_a_time_kernel(scene: SceneData, recv: ReceiverData, n: wp.int32, fn: wp.uint64, scn: wp.uint64,
                         out: wp.array2d(dtype=wp.int32)):
    """Each shadow ray alone: through warpis's tree (``_any``, as ``any_hit_between``) where
    ``fn`` is 0, else through Embree's rtcOccluded1 at address ``fn`` on scene ``scn``."""
    i, j = wp.tid()
    sp = shading_point(scene, recv, i)
    s = stream(wp.uint32(1), i, j, 0)
    visible = wp.int32(0)
    for q in range(n):
        smp = sample_light_point(LIGHT_AREA, scene, sp, wp.vec2(uniform(s, q, 0), uniform(s, q, 1)))
        r, planes, length = shadow_ray(scene, sp.p, sp.n, sp.ng, sp.slab, smp.w, smp.emitter, smp.t)
        if wp.dot(sp.n, smp.w) > 0.0 and length > 0.0:
            blocked = bool(False)  # noqa: UP018 (a Warp variable the branches below assign)
            if fn == wp.uint64(0):
                blocked = bvh._any(scene.bvh, scene.mesh, r, smp.w, length, planes)
            else:
                blocked = embree_occluded(fn, scn, r.o, smp.w, length)
            if not blocked:
                visible += 1
    out[i, j] = visible


ROBUST = 1 << 2  # RTC_SCENE_FLAG_ROBUST (rtcore_scene.h): watertight traversal, no reduced accuracy


class Embree:
    """Embree 4 through ctypes: the library embreex bundles, one device, scenes of triangles."""

    def __init__(self) -> None:
        import embreex  # the bench extra

        (path,) = glob.glob(os.path.join(os.path.dirname(embreex.__file__) + ".libs", "libembree4*"))
        lib = self.lib = ctypes.CDLL(path)
        vp = ctypes.c_void_p
        lib.rtcNewDevice.restype = vp
        lib.rtcNewDevice.argtypes = [ctypes.c_char_p]
        lib.rtcNewScene.restype = vp
        lib.rtcNewScene.argtypes = [vp]
        lib.rtcSetSceneFlags.argtypes = [vp, ctypes.c_int]
        lib.rtcNewGeometry.restype = vp
        lib.rtcNewGeometry.argtypes = [vp, ctypes.c_int]
        lib.rtcSetNewGeometryBuffer.restype = vp
        lib.rtcSetNewGeometryBuffer.argtypes = [vp, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t,
                                                ctypes.c_size_t]
        lib.rtcAttachGeometry.restype = ctypes.c_uint
        lib.rtcAttachGeometry.argtypes = [vp, vp]
        for name in ("rtcCommitGeometry", "rtcReleaseGeometry", "rtcCommitScene"):
            getattr(lib, name).argtypes = [vp]
        self.device = lib.rtcNewDevice(None)
        self.occluded = ctypes.cast(lib.rtcOccluded1, vp).value

    def scene(self, vertices: np.ndarray, triangles: np.ndarray) -> int:
        """A committed scene of the triangles (float32 corners, as warpis's): its handle."""
        lib = self.lib
        scn = lib.rtcNewScene(self.device)
        lib.rtcSetSceneFlags(scn, ROBUST)
        geometry = lib.rtcNewGeometry(self.device, 0)  # RTC_GEOMETRY_TYPE_TRIANGLE
        v = np.ascontiguousarray(vertices, np.float32)
        t = np.ascontiguousarray(triangles, np.uint32)
        ctypes.memmove(lib.rtcSetNewGeometryBuffer(geometry, 1, 0, 0x9003, 12, len(v)), v.ctypes.data, v.nbytes)
        ctypes.memmove(lib.rtcSetNewGeometryBuffer(geometry, 0, 0, 0x5003, 12, len(t)), t.ctypes.data, t.nbytes)
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(scn, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(scn)
        return scn



def timed(kernel, up, receivers: int, trials: int, n: int, extra: tuple = ()) -> tuple[float, np.ndarray]:
    """(rays per second, visible counts) of one launch."""
    out = wp.zeros((receivers, trials), dtype=wp.int32, device="cpu")
    start = time.perf_counter()
    wp.launch(kernel, dim=(receivers, trials), inputs=[up.data, up.receiver_data, n, *extra, out], device="cpu")
    wp.synchronize_device("cpu")
    return receivers * trials * n / (time.perf_counter() - start), out.numpy()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["occluded-quad", "heavy-occluder"])
    parser.add_argument("--n", type=int, default=64, help="samples per trial (a multiple of 4)")
    parser.add_argument("--trials", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    if args.n % 4:
        parser.error("--n must be a multiple of 4")
    wp.config.quiet = True
    wp.load_module(one_at_a_time_kernel.module, device="cpu")
    try:
        embree: Embree | None = Embree()
    except (ImportError, OSError, ValueError) as e:
        embree = None
        print(f"Embree left out: {e}")
    print(f"load {os.getloadavg()[0]:.2f}; M rays/s, one thread, medians of {args.repeat}")
    for name in args.scenes:
        scene = warpis.load_scene(name)
        up = upload(scene)
        sides = [("one at a time", one_at_a_time_kernel, (wp.uint64(0), wp.uint64(0))),
                 ("four together", packet_kernel, ())]
        if embree is not None:
            handle = embree.scene(scene.vertices, scene.triangles)
            sides.append(("Embree", one_at_a_time_kernel, (wp.uint64(embree.occluded), wp.uint64(handle))))
        rates: dict[str, list[float]] = {label: [] for label, _, _ in sides}
        for _ in range(args.repeat):
            counts = {}
            for label, kernel, extra in sides:
                rate, counts[label] = timed(kernel, up, len(scene.receivers), args.trials, args.n, extra)
                rates[label].append(rate / 1e6)
            if not np.array_equal(counts["one at a time"], counts["four together"]):
                raise SystemExit(f"{name}: the packet kernel sees other rays blocked than the scalar one")
        one = statistics.median(rates["one at a time"])
        line = f"{name:16s} one at a time {one:6.2f}"
        for label in list(rates)[1:]:
            rate = statistics.median(rates[label])
            line += f"   {label} {rate:6.2f} ({rate / one:.2f}×)"
        print(line)
        if embree is not None:
            diff = counts["Embree"] - counts["one at a time"]
            print(f"{'':16s} Embree's visible counts differ in {np.count_nonzero(diff)} of {diff.size} trials "
                  f"(at least {int(np.abs(diff).sum())} of {diff.size * args.n} rays)")
    print(f"load {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
