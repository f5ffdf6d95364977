"""Mutation check: plant known, physically meaningful bugs one at a time; the suite must catch each.

Each mutant names a function of warpis (or of its tests' subjects) and a unique expression
inside it — a stable anchor, not a line number — and what to put in its place.  The
script copies the project into a temporary folder, plants one mutant there, runs only the
test files that should catch it (``pytest -x``, so it stops at the first failure) with
that copy first on ``PYTHONPATH``, restores the file, and goes on.  ``--jobs J`` (default:
one per core) keeps J copies and runs J mutants at once, one per copy: a mutant's run is
mostly one thread (pytest, a kernel's compilation, numpy), so two at a time keep both
cores of a two-core machine busy.

A mutant is *killed* when a test fails; it *survives* when the tests pass.  The script
exits 1 when any mutant survives, when an anchor is no longer found exactly once (a
refactor moved it: update the mutant), or when the unmutated copy already fails the
selected tests (a kill would then prove nothing).  A mutant that breaks the build (a
collection error, a kernel that does not compile) is reported as *broken*, also exit 1:
it proves nothing either.

    python scripts/mutants.py                 # every mutant, two at a time on 2 cores
    python scripts/mutants.py --list          # names and bugs
    python scripts/mutants.py balance-plus-one trials-share-a-stream
    python scripts/mutants.py --markdown      # the result table as Markdown (docs/development.md, notes)

Not part of CI: it recompiles Warp kernels for most mutants.
"""

from __future__ import annotations

import argparse
import ast
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COPIED = ("warpis", "tests", "scripts", "meshes", "docs", "pyproject.toml", "README.md")


@dataclass(frozen=True)
class Mutant:
    name: str
    bug: str  # what it plants, in words
    file: str  # relative to the repository root
    function: str  # the def whose body holds the anchor (nested defs count)
    old: str  # occurs exactly once in that function
    new: str
    tests: tuple[str, ...]  # test files (or node ids) that must catch it


K = "warpis/kernels/"
MUTANTS: tuple[Mutant, ...] = (
    # ------------------------------------------------------------------ combiners (estimators.py)
    Mutant("balance-plus-one", "balance divides its sum by m·N_g + 1", K + "estimators.py", "stratified_trial",
           "return total / wp.float64(m * n_g)", "return total / wp.float64(m * n_g + 1)",
           ("tests/test_estimators.py",)),
    Mutant("power-as-balance", "the power heuristic becomes balance (exponent 1; still unbiased)",
           K + "estimators.py", "stratified_trial",
           "wp.float64(f * pdf / other_pdfs(techs, k, pdf, scene, table, sp, w, 2))",
           "wp.float64(f / other_pdfs(techs, k, pdf, scene, table, sp, w, 1))",
           ("tests/test_theory.py",)),
    Mutant("single-weight-off", "single IS weights f/(1.02·g)", K + "estimators.py", "stratified_trial",
           "if combiner == SINGLE:\n                                total = total + wp.float64(f / pdf)",
           "if combiner == SINGLE:\n                                total = total + wp.float64(f / (1.02 * pdf))",
           ("tests/test_estimators.py",)),
    Mutant("mixture-pick-reuses-stream", "the mixture picks its technique from the sample's own stream",
           K + "estimators.py", "mixture_trial",
           "k = wp.min(wp.int32(uniform(s_pick, i, 0) * float(n_g)), n_g - 1)",
           "k = wp.min(wp.int32(uniform(s, i, 0) * float(n_g)), n_g - 1)",
           ("tests/test_estimators.py",)),
    Mutant("biased-divides-by-pdf", "biased IS weights f/g (becomes unbiased IS, converges to F, not ∫ f g)",
           K + "estimators.py", "stratified_trial",
           "total = total + wp.float64(f)\n",
           "total = total + wp.float64(f / technique_pdf(techs[k], scene, table, sp, w))\n",
           ("tests/test_theory.py", "tests/test_estimators.py")),
    Mutant("maximum-becomes-minimum", "the maximum heuristic keeps the sample whose pdf is the smallest (its "
           "weights still sum to 1, but land on techniques that cannot sample there)", K + "estimators.py", "largest_pdf", "if g > pdf_k or (j < k and g == pdf_k):",
           "if g < pdf_k or (j < k and g == pdf_k):", ("tests/test_estimators.py",)),
    Mutant("trials-share-a-stream", "consecutive trials share one random stream (trial → trial // 2)",
           K + "estimators.py", "stratified_trial",
           "s = stream(seed, sp.receiver, trial, k)", "s = stream(seed, sp.receiver, trial / 2, k)",
           ("tests/test_rng.py",)),
    # ------------------------------------------------------------------ patterns (patterns.py)
    Mutant("jittered-lower-half", "jittered points only in the lower half of each cell", K + "patterns.py",
           "jittered_point", "y = (float(r) + uniform(s, cell, 1)) / float(rows)",
           "y = (float(r) + 0.5 * uniform(s, cell, 1)) / float(rows)", ("tests/test_estimators.py",)),
    Mutant("independent-on-diagonal", "independent points reuse one coordinate (u on the diagonal)",
           K + "patterns.py", "pattern_point", "return wp.vec2(uniform(s, i, 0), uniform(s, i, 1))",
           "return wp.vec2(uniform(s, i, 0), uniform(s, i, 0))", ("tests/test_estimators.py",)),
    Mutant("antithetic-without-reflection", "antithetic pairs repeat u instead of reflecting it (still unbiased)",
           K + "patterns.py", "pattern_point", "            return reflect(u)\n", "            return u\n",
           ("tests/test_theory.py",)),
    Mutant("jittered-antithetic-wrong-mirror", "jittered-antithetic reflects the point of its own cell",
           K + "patterns.py", "pattern_point", "return reflect(jittered_point(s, m - 1 - i, rows, cols))",
           "return reflect(jittered_point(s, i, rows, cols))", ("tests/test_estimators.py",)),
    Mutant("jittered-theory-strips", "the theory lays jittered cells as 1 × m strips, the kernel as a grid",
           K + "patterns.py", "_cells", "return Blocks(m, 1, grid_shape(m), False)",
           "return Blocks(m, 1, (1, m), False)", ("tests/test_theory.py",)),
    Mutant("lhs-one-permutation", "LHS takes its rows from the permutation of its columns (points on the diagonal)",
           K + "patterns.py", "lhs_point", "cy = shuffle_index(wp.uint32(i), wp.uint32(m), pattern_hash(s, 2))",
           "cy = cx", ("tests/test_point_sets.py",)),
    Mutant("cmj-fine-row-from-the-row", "CMJ's fine row permutes the coarse row instead of the column",
           K + "patterns.py", "cmj_point", "sx = permute(cx, wp.uint32(cols), pattern_hash(s, 2))",
           "sx = permute(cy % wp.uint32(cols), wp.uint32(cols), pattern_hash(s, 2))", ("tests/test_point_sets.py",)),
    Mutant("sobol-second-dimension-is-van-der-corput", "Sobol's second coordinate repeats the first's direction "
           "numbers (each point still uniform; no longer a net)", K + "patterns.py", "sobol_2d",
           "v = v ^ (v >> wp.uint32(1))", "v = v >> wp.uint32(1)", ("tests/test_point_sets.py",)),
    Mutant("halton-base-3-unscrambled", "Halton's base-3 digits left unscrambled", K + "patterns.py",
           "owen_radical_inverse_base3", "h = mix32(seed ^ mix32(prefix)) % wp.uint32(6)", "h = wp.uint32(0)",
           ("tests/test_point_sets.py",)),
    Mutant("lattice-one-shift", "the lattice shifts both coordinates by the same amount", K + "patterns.py",
           "lattice_point", "+ unit_float(pattern_hash(s, 2))", "+ unit_float(pattern_hash(s, 1))",
           ("tests/test_point_sets.py",)),
    Mutant("user-pattern-not-dispatched", "a registered pattern's code falls through to the built-in branches",
           K + "patterns.py", "_with_user_point", "return user_point(s, i, m)",
           "return inner(pattern, s, i, m, rows, cols)", ("tests/test_user_pattern.py",)),
    # ------------------------------------------------------------------ techniques (warps.py, techniques.py)
    Mutant("uniform-pdf-constant", "uniform hemisphere pdf 1.01/(2π)", K + "warps.py", "uniform_hemisphere_pdf",
           "INV_2PI, 0.0)", "INV_2PI * 1.01, 0.0)", ("tests/test_pdf_integrals.py",)),
    Mutant("cosine-pdf-constant", "cosine pdf × 1.01", K + "warps.py", "cosine_hemisphere_pdf",
           "return wp.max(cos_theta, 0.0) * INV_PI", "return wp.max(cos_theta, 0.0) * INV_PI * 1.01",
           ("tests/test_pdf_integrals.py",)),
    Mutant("phong-pdf-normalisation", "Phong lobe pdf (e+2)/(2π) instead of (e+1)/(2π)", K + "warps.py",
           "phong_lobe_pdf", "(exponent + 1.0) * INV_2PI", "(exponent + 2.0) * INV_2PI",
           ("tests/test_pdf_integrals.py",)),
    Mutant("light-pdf-without-r2", "light pdf without the distance squared", K + "techniques.py",
           "area_to_solid_angle", "return density * t * t / cos_y", "return density / cos_y",
           ("tests/test_light_pdf.py",)),
    Mutant("light-pdf-receiver-cosine", "light pdf with the receiver's cosine instead of the light's",
           K + "techniques.py", "add_crossing", "area_to_solid_angle(light_density(tech, scene, radiance), t, nrm, w)",
           "area_to_solid_angle(light_density(tech, scene, radiance), t, sp.n, w)",
           ("tests/test_light_pdf.py", "tests/test_baseline.py")),
    Mutant("light-area-forgets-pick", "light-area density 1/A_triangle (the triangle's pick probability lost)",
           K + "techniques.py", "add_crossing", "area_to_solid_angle(light_density(tech, scene, radiance), t, nrm, w)",
           "area_to_solid_angle(2.0 / wp.length(nrm), t, nrm, w)", ("tests/test_light_pdf.py",)),
    Mutant("light-power-picks-by-area", "light-power's pdf picks triangles by area while sampling by power",
           K + "techniques.py", "light_density", "return radiance / scene.total_power",
           "return 1.0 / scene.total_area", ("tests/test_light_pdf.py",)),
    Mutant("light-solid-angle-ignores-radiance", "light-solid-angle's pdf forgets the radiance of the pick",
           K + "techniques.py", "add_crossing", "out.pdf = out.pdf + radiance / float(table.total[sp.receiver])",
           "out.pdf = out.pdf + 1.0 / float(table.total[sp.receiver])",
           ("tests/test_light_pdf.py",)),
    # ------------------------------------------------------------------ sphere lights (spheres.py, techniques.py)
    Mutant("sphere-cone-without-2pi", "a sphere light's cone solid angle loses its 2π: Ω = 1 − cos θmax, so its "
           "pick probability and its pdf L/W are off", K + "techniques.py", "sphere_solid_angle",
           "return wp.float64(2.0) * wp.float64(PI64) * one_minus_cos_max(p, c, r)",
           "return one_minus_cos_max(p, c, r)", ("tests/test_sphere_lights.py",)),
    Mutant("sphere-cone-cancels", "1 − cos θmax computed as 1 − √(1 − sin²θmax), which cancels for far spheres",
           K + "spheres.py", "one_minus_cos_max", "return sin2 / (wp.float64(1.0) + cos_max)",
           "return wp.float64(float(1.0) - float(cos_max))", ("tests/test_sphere_lights.py",)),
    Mutant("sphere-samples-off-the-rim", "cone and surface samples that float32 rounding carries off the silhouette "
           "are left there (lost)", K + "spheres.py", "into_sphere", "if roots[1] > wp.float64(0.0):",
           "if True:", ("tests/test_sphere_lights.py",)),
    Mutant("sphere-far-side-not-counted", "light-area's pdf counts only a sphere's near crossing",
           K + "techniques.py", "sphere_light_pdf", "for i in range(2):", "for i in range(1):",
           ("tests/test_sphere_lights.py",)),
    Mutant("sphere-does-not-block", "a sphere never blocks a shadow ray", K + "spheres.py", "_crosses",
           "return (t0 > t_min and t0 < t_max) or (t1 > t_min and t1 < t_max)", "return False",
           ("tests/test_sphere_lights.py",)),
    # ------------------------------------------------------------------ environment lights (environment.py)
    Mutant("envmap-pdf-misses-jacobian", "the envmap pdf divides the cell's probability by ΔφΔθ, not by its solid "
           "angle Δφ(cos θ_j − cos θ_j+1): the sin θ Jacobian is lost", K + "environment.py", "environment_pdf",
           "return float(p / _cell_solid_angle(env, j))",
           "return float(p / (wp.float64(TWO_PI) / wp.float64(columns - 1) * wp.float64(PI) / wp.float64(height - 1)))",
           ("tests/test_pdf_integrals.py",)),
    Mutant("envmap-pdf-of-the-next-row", "the envmap pdf takes the probability of the row below the direction's",
           K + "environment.py", "environment_pdf", "p = (env.row_cdf[j + 1] - env.row_cdf[j])",
           "p = (env.row_cdf[wp.min(j + 2, height - 1)] - env.row_cdf[j + 1])", ("tests/test_pdf_integrals.py",)),
    Mutant("envmap-lookup-without-half-texel", "the lookup drops Mitsuba's half-texel shift: every texel is read "
           "half a texel to the east", K + "environment.py", "environment_uv",
           "u = wp.atan2(v[0], -v[2]) * INV_2PI - 0.5 / (columns - 1.0)", "u = wp.atan2(v[0], -v[2]) * INV_2PI",
           ("tests/test_environment.py",)),
    Mutant("delta-light-without-shadows", "a delta light's term skips its shadow ray: the box never hides the "
           "bulb or the sun", K + "integrand.py", "delta_term",
           "if length > 0.0 and any_hit_between(", "if length < 0.0 and any_hit_between(",
           ("tests/test_delta_lights.py",)),
    # ------------------------------------------------------------------ light samples, shadow rays, the BVH
    Mutant("fast-light-pdf-without-r2", "a light sample on a planar emitter set reports its pdf without t²",
           K + "techniques.py", "sample_light_point", "* t * t / cos_y", "/ cos_y", ("tests/test_light_paths.py",)),
    Mutant("every-emitter-set-planar", "sphere lights and lights in several planes taken for one planar set",
           K + "device.py", "_scene_data", "d.planar_emitters = int(len(scene.sphere_lights) == 0 and planar_emitters(",
           "d.planar_emitters = 1 + 0 * int(len(scene.sphere_lights) == 0 and planar_emitters(",
           ("tests/test_light_paths.py",)),
    Mutant("light-sample-lit-from-behind", "a planar light's back face emits (light samples and lookups)",
           K + "integrand.py", "integrand_via",
           "if k >= 0 and t > lead and wp.dot(scene.emitter_normal[k], w) < 0.0:", "if k >= 0 and t > lead:",
           ("tests/test_light_paths.py",)),
    Mutant("shadow-ray-into-the-light", "the shadow ray runs into the emitter's slab and hits the light itself",
           K + "integrand.py", "radiance_unless_blocked", "length = t - lead - tail", "length = t - lead + tail",
           ("tests/test_light_paths.py",)),
    Mutant("bvh-box-test-not-widened", "the box test without its rounding margin: flat boxes are missed",
           K + "bvh.py", "_entries", "wp.where(t_near <= t_far * FAR_WIDEN, t_near, INFINITY)",
           "wp.where(t_near < t_far, t_near, INFINITY)", ("tests/test_bvh.py",)),
    Mutant("bvh-leaf-drops-a-slot", "the closest-hit leaf test skips each leaf's fourth triangle",
           K + "bvh.py", "_leaf_hit", "for i in range(4):", "for i in range(3):", ("tests/test_bvh.py",)),
    Mutant("bvh-emitters-not-apart", "the build files the emitters with the rest of the mesh",
           K + "bvh.py", "build_wide_bvh", "if chosen.any() and not chosen.all():", "if False:",
           ("tests/test_bvh.py",)),
    Mutant("self-hit-receiver-plane-kept", "shadow and closest-hit rays no longer ignore the receiver's own plane",
           K + "bvh.py", "_ignored", "return coplanar(p0, p1, p2, planes.a, planes.na) or ",
           "return False or ", ("tests/test_self_hit.py",)),
    Mutant("self-hit-emitter-plane-kept", "shadow rays no longer ignore the emitter's own plane at their end",
           K + "bvh.py", "_ignored", " or coplanar(p0, p1, p2, planes.b, planes.nb)", "",
           ("tests/test_self_hit.py",)),
    Mutant("self-hit-slab-from-own-triangle", "the receiver's slab counts its own (coplanar) triangles again",
           K + "device.py", "_slab_kernel", "            if not coplanar(p0, p1, p2, x, nx):\n                scale",
           "            if True:\n                scale", ("tests/test_self_hit.py",)),
    Mutant("self-hit-hidden-light-not-refused", "a slab that would hide a light is used instead of refused",
           K + "device.py", "_slab_kernel", "hidden[r] = 3 * face + 2", "hidden[r] = -1",
           ("tests/test_self_hit.py",)),
    Mutant("shadow-ray-plane-of-the-shading-normal", "shadow rays take the shading normal for the surface's own "
           "plane, so the surface blocks rays that leave through it", K + "integrand.py", "integrand_via",
           "le = radiance_unless_blocked(scene, sp.p, sp.ng, w, lead, k, t)",
           "le = radiance_unless_blocked(scene, sp.p, sp.n, w, lead, k, t)", ("tests/test_vertex_normals.py",)),
    Mutant("rays-stop-at-the-geometric-plane", "rays above the shading horizon but below the surface's own plane "
           "see nothing (Mitsuba casts them through the surface)", K + "integrand.py", "integrand_via",
           "lead = sp.slab / wp.max(wp.abs(wp.dot(sp.ng, w)), 1.0e-12)",
           "lead = sp.slab / wp.max(wp.dot(sp.ng, w), 1.0e-12)",
           ("tests/test_vertex_normals.py", "tests/test_shading_normals.py")),
    Mutant("camera-pixels-shade-flat", "camera pixels shade with their triangle's normal, not the interpolated one",
           "warpis/scenes/camera.py", "cast_camera", "    if corner_normals is not None and len(flat):\n",
           "    if False:\n", ("tests/test_vertex_normals.py",)),
    # ------------------------------------------------------------------ materials (integrand.py)
    Mutant("phong-brdf-normalisation", "Phong BRDF (e+1)/(2π) instead of (e+2)/(2π)", K + "integrand.py", "brdf",
           "sp.albedo * (sp.exponent + 2.0) * INV_2PI", "sp.albedo * (sp.exponent + 1.0) * INV_2PI",
           ("tests/test_materials.py",)),
    Mutant("lambert-ignores-albedo", "Lambert ρ = 1/π whatever the albedo", K + "integrand.py", "brdf",
           "return sp.albedo * INV_PI", "return INV_PI", ("tests/test_materials.py",)),
    Mutant("irradiance-over-pi", "the irradiance material ρ = 1/π instead of 1", K + "integrand.py", "brdf",
           "    return 1.0\n", "    return INV_PI\n", ("tests/test_materials.py",)),
    # ------------------------------------------------------------------ microfacet materials (microfacet.py)
    Mutant("microfacet-jacobian-halved", "the reflection Jacobian 1/(2 wo·h) instead of 1/(4 wo·h) (all normals)",
           K + "microfacet.py", "specular_pdf", "/ (4.0 * wp.dot(wo, h))", "/ (2.0 * wp.dot(wo, h))",
           ("tests/test_microfacet.py",)),
    Mutant("conductor-channels-share-eta", "every channel's Fresnel term uses the first channel's eta",
           K + "microfacet.py", "conductor_brdf", "fresnel_conductor(c, sp.eta[2], sp.k[2])",
           "fresnel_conductor(c, sp.eta[0], sp.k[2])", ("tests/test_microfacet.py",)),
    Mutant("plastic-ignores-internal-scattering", "roughplastic's diffuse term without 1/(1 − R_int)",
           K + "microfacet.py", "plastic_brdf", "sp.albedo / (1.0 - internal)", "sp.albedo",
           ("tests/test_microfacet.py",)),
    Mutant("plastic-pdf-one-lobe", "roughplastic's pdf forgets the diffuse lobe's share",
           K + "microfacet.py", "plastic_pdf", "p_spec * spec + (1.0 - p_spec) * wo_l[2] * INV_PI", "p_spec * spec",
           ("tests/test_microfacet.py",)),
    Mutant("bsdf-technique-cosine-for-plastic", "the bsdf technique's pdf at roughplastic is the cosine density",
           K + "techniques.py", "bsdf_pdf", "return plastic_pdf(scene.plastic_table, sp, w)",
           "return cosine_hemisphere_pdf(wp.dot(w, sp.n))", ("tests/test_materials.py",)),
    # ------------------------------------------------------------------ Mitsuba scenes (scenes/mitsuba/)
    Mutant("mitsuba-ignores-flip-normals", "analytic shapes ignore flip_normals (light from the wrong side)",
           "warpis/scenes/mitsuba/shapes.py", "_geometry", "-1.0 if flipped else 1.0", "1.0",
           ("tests/test_mitsuba_scene.py",)),
    # ------------------------------------------------------------------ camera receivers (scenes/camera.py)
    Mutant("camera-pixel-corner", "primary rays through pixel corners instead of centres",
           "warpis/scenes/camera.py", "directions", "x = ((np.arange(self.width) + 0.5)",
           "x = ((np.arange(self.width) + 0.0)", ("tests/test_camera.py",)),
    Mutant("camera-backs-shaded", "the back of a one-sided surface becomes a receiver (Mitsuba gives 0)",
           "warpis/scenes/camera.py", "cast_camera", "back = (ds > 0) & ~np.asarray(two_sided, bool)[own]",
           "back = (ds > 0) & np.zeros(len(two_sided), bool)[own]", ("tests/test_camera.py",)),
    # ------------------------------------------------------------------ images (runs/image.py)
    Mutant("image-efficiency-ignores-cost", "efficiency 1/variance, the time per estimate forgotten",
           "warpis/runs/image.py", "assemble", "eff = 1.0 / (var * cost)", "eff = 1.0 / var",
           ("tests/test_image.py",)),
    Mutant("image-tile-key-ignores-seed", "a tile's file name leaves out the seed (another seed's tiles are read)",
           "warpis/runs/image.py", "measure", "run.n, run.trials, run.seed, tile.start", "run.n, run.trials, tile.start",
           ("tests/test_image.py",)),
    # ------------------------------------------------------------------ optimal MIS and cutoff (estimators.py)
    Mutant("optimal-failure-adds-alpha", "a failed sample of the optimal combiners adds +α_k instead of −α_k",
           K + "estimators.py", "optimal_terms", "t[k] = wp.float64(1.0)", "t[k] = wp.float64(-1.0)",
           ("tests/test_estimators.py::test_optimal_mis_replayed_where_samples_fail", "tests/test_optimal_mis.py")),
    Mutant("optimal-drops-alpha-sum", "optimal MIS forgets its Σ α_k term (biased by Σ α_k)", K + "estimators.py",
           "optimal_trial", "return alpha[0] + alpha[1] + alpha[2] + alpha[3] + total / wp.float64(m)",
           "return total / wp.float64(m)", ("tests/test_optimal_mis.py", "tests/test_estimators.py")),
    Mutant("pilot-reuses-main-stream", "the pilot draws the main samples' random numbers (α correlated with them)",
           K + "estimators.py", "pilot_alpha", "s = stream(seed, sp.receiver, trial, PILOT_STREAM + k)",
           "s = stream(seed, sp.receiver, trial, k)", ("tests/test_estimators.py",)),
    Mutant("pilot-without-ridge", "the pilot solves Â α = b̂ without its ridge (unbounded α, heavy tails)",
           K + "estimators.py", "pilot_alpha", "ridge = PILOT_RIDGE * trace / wp.float64(n_g)",
           "ridge = wp.float64(0.0)",
           ("tests/test_estimators.py::test_trial_kernel_equals_each_combiners_formula_replayed_in_numpy",)),
    Mutant("cutoff-keeps-the-small", "cutoff keeps the techniques below α·g_max instead of those above",
           K + "estimators.py", "cutoff_sum", "if pdf_k < floor:", "if pdf_k >= floor:",
           ("tests/test_optimal_mis.py", "tests/test_estimators.py")),
    Mutant("optimal-twin-failure-sign", "the theory's optimal ψ adds +N_g α_k at a failed sample",
           K + "estimators.py", "_optimal_weights", "return np.where(pdf[:, k] > 0, value, -n_g * ctx.alpha[:, k])",
           "return np.where(pdf[:, k] > 0, value, n_g * ctx.alpha[:, k])",
           ("tests/test_optimal_mis.py::test_the_theorys_psi_counts_every_sample_and_a_failed_one_as_minus_ng_alpha",)),
    # ------------------------------------------------------------------ point sets (patterns.py, point_sets)
    Mutant("shuffle-two-rounds", "the lhs row shuffle runs 2 rounds (pair law far from uniform)", K + "patterns.py",
           "shuffle_index", "for r in range(SHUFFLE_ROUNDS):", "for r in range(2):",
           ("tests/test_point_sets.py",)),
    Mutant("lhs-form-drops-cell-term", "the Latin hypercube's variance forgets the within-cell difference D",
           "warpis/point_sets/lhs.py", "_replica_terms", "return m * w + m / (m - 1) * (m * k - d)",
           "return m * w + m / (m - 1) * (m * k)", ("tests/test_lhs_lattice_variance.py",)),
    Mutant("lattice-form-drops-set-spread", "the lattice's variance forgets the spread of its sets' means",
           "warpis/point_sets/lattice.py", "_jackknife", "value = a.mean(axis=-1) + big_d[..., 0] / (k - 1)",
           "value = a.mean(axis=-1)", ("tests/test_lhs_lattice_variance.py",)),
    Mutant("net-gain-base-two", "Owen's gains use base 2 for Halton's base-3 coordinate", "warpis/point_sets/nets.py",
           "_gain_parts", "num = _exactly(_exactly(n, b1, 0), b2, 1)", "num = _exactly(_exactly(n, b1, 0), 2, 1)",
           ("tests/test_net_variance.py",)),
    # ------------------------------------------------------------------ random numbers (rng.py)
    Mutant("rng-chain-drops-shift", "the Warp generator's chain loses its h << 8 term (the twin keeps it)",
           K + "rng.py", "chain", "return mix32(h ^ (wp.uint32(value) + _GOLDEN + (h << _S8)))",
           "return mix32(h ^ (wp.uint32(value) + _GOLDEN))", ("tests/test_rng.py",)),
    # ------------------------------------------------------------------ analysis
    Mutant("eq14-printed-without-ng2", "printed eq. 14 without the 1/N_g² on ΣJ²", "warpis/analysis/theory.py",
           "_eq14_printed", "stratum_integrals(c.scene, c.receiver, c.est.techniques, m) / n_g",
           "stratum_integrals(c.scene, c.receiver, c.est.techniques, m)", ("tests/test_theory.py",)),
    Mutant("block-variance-squared-mean", "exact variance subtracts the squared replica mean (biased by Var(p̄))",
           "warpis/analysis/quadrature.py", "_unbiased_block_variance",
           "pairs = (sp * sp - (p * p).sum(axis=-1)) / (r * (r - 1))", "pairs = (sp / r) ** 2",
           ("tests/test_theory_batched.py", "tests/test_theory.py")),
    Mutant("interval-se-narrow", "the variance interval's se × 0.9", "warpis/stats.py", "_interval",
           "se = np.sqrt(np.maximum(var_s2, 0.0))", "se = 0.9 * np.sqrt(np.maximum(var_s2, 0.0))",
           ("tests/test_stats.py",)),
    Mutant("interval-normal-theory", "the variance interval assumes normal estimates (μ4 = 3σ⁴)",
           "warpis/stats.py", "_interval", "var_s2 = (m4 - s2 * s2 * (m - 3) / (m - 1)) / m",
           "var_s2 = 2 * s2 * s2 / (m - 1)", ("tests/test_stats.py",)),
    Mutant("reference-stderr-halved", "quadrature references report half their standard error",
           "warpis/analysis/reference.py", "_run", "float(row.std(ddof=1) / math.sqrt(replicas))",
           "float(0.5 * row.std(ddof=1) / math.sqrt(replicas))", ("tests/test_reference_precision.py",)),
    Mutant("memo-name-forgets-the-arguments", "a kept theory result is named without its arguments: another "
           "receiver or N reads it back", "warpis/analysis/memo.py", "kept_path",
           "(_FORMAT, quantity, digest, device, args, code)", "(_FORMAT, quantity, digest, device, code)",
           ("tests/test_memo.py",)),
    Mutant("memo-name-forgets-the-code", "a kept theory result outlives a change of warpis's code",
           "warpis/analysis/memo.py", "code_digest", "h.update(hashlib.sha256(path.read_bytes()).digest())",
           "h.update(b\"\")", ("tests/test_memo.py",)),
    Mutant("memo-prunes-its-own-version", "pruning the theory cache counts the running code's own folder among "
           "the old ones", "warpis/analysis/memo.py", "_prune", "(f for f in folders if f[1] != str(current))",
           "(f for f in folders)", ("tests/test_memo.py",)),
    Mutant("recent-values-forget-the-technique", "the quadrature's reused evaluations are keyed without the "
           "technique: technique 1 reads technique 0's values", "warpis/analysis/quadrature.py", "_recent_values",
           "int(rows[0]), k, every,", "int(rows[0]), every,", ("tests/test_memo.py",)),
    Mutant("moments-together-columns-in-union-order", "moments of several technique sets read each set's pdf "
           "columns in the union's order, not the set's", "warpis/analysis/quadrature.py", "for_set",
           "pdf[:, [self.union.index(name) for name in techniques]]",
           "pdf[:, sorted(self.union.index(name) for name in techniques)]", ("tests/test_memo.py",)),
    Mutant("cluster-moments-of-the-first-set", "on a Dask cluster every technique set of a receiver gets the "
           "moments of its first", "warpis/runs/cluster.py", "_submit", "client.submit(pick, group, i, pure=False)",
           "client.submit(pick, group, 0, pure=False)", ("tests/test_cluster.py",)),
    Mutant("run-moments-under-another-set", "a run's moments found together are filed under the wrong "
           "technique sets (in reverse order)", "warpis/runs/cell.py", "moments_of",
           "zip(wanted, moments_together", "zip(wanted[::-1], moments_together", ("tests/test_memo.py",)),
    # ------------------------------------------------------------------ runs
    Mutant("inside-band-widened", "verify's inside band 3 × 1.96", "warpis/runs/cell.py", "inside",
           "return bool(abs(z) <= Z95)", "return bool(abs(z) <= 3 * Z95)", ("tests/test_verify_verdicts.py",)),
    Mutant("helper-figures-dropped", "the figures a second process draws are left out of the study's list "
           "(its report links fewer)", "warpis/plots.py", "draw_all", "made[i] = future.result()", "future.result()",
           ("tests/test_outputs.py",)),
    Mutant("resume-drops-last-row", "resume drops the last finished row of each cell", "warpis/runs/study.py",
           "_resume", "done = {c.key: previous[c.key] for c in cells", "done = {c.key: previous[c.key][:-1] for c in cells",
           ("tests/test_study.py",)),
    Mutant("side-by-side-receivers-out-of-order", "a cell's receivers, scored two at a time, get their "
           "results in reverse order", "warpis/runs/cell.py", "each_receiver",
           "[pool.submit(work, r) for r in receivers]", "[pool.submit(work, r) for r in receivers][::-1]",
           ("tests/test_cell.py",)),
    Mutant("side-by-side-receivers-share-moments", "every receiver of a cell is predicted from the first "
           "receiver's moments", "warpis/runs/cell.py", "score_cell",
           "moments[row.receiver]", "moments[rows[0].receiver]", ("tests/test_cell.py",)),
    # ------------------------------------------------------------------ warpis check
    Mutant("check-pdf-tolerance-ignored", "warpis check passes a reported pdf whatever it differs by",
           "warpis/check/checks.py", "pdf_at_sample", "passed = frac <= PDF_MISMATCH_FRACTION", "passed = True",
           ("tests/test_check.py",)),
    Mutant("check-family-dropped", "warpis check holds each statistical test at the run's family-wise level "
           "(no Šidák correction)", "warpis/check/checks.py", "per_test",
           "return sidak_threshold(self.alpha, max(1, self.tests))", "return self.alpha", ("tests/test_check.py",)),
    Mutant("check-window-without-jacobian", "the windowed sphere's quadrature forgets the magnification's Jacobian",
           "warpis/check/window.py", "_points", "return d, (self.dc * self.dphi / (per * per)) / jac",
           "return d, self.dc * self.dphi / (per * per)", ("tests/test_check.py",)),
)


class AnchorError(Exception):
    pass


def plant(text: str, mutant: Mutant) -> str:
    """``text`` (the file) with the mutant's anchor replaced, or AnchorError."""
    defs = [n for n in ast.walk(ast.parse(text)) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
            and n.name == mutant.function]
    if len(defs) != 1:
        raise AnchorError(f"{mutant.file}: {len(defs)} functions named {mutant.function!r} (expected 1)")
    lines = text.splitlines(keepends=True)
    start, end = defs[0].lineno - 1, defs[0].end_lineno
    body = "".join(lines[start:end])
    count = body.count(mutant.old)
    if count != 1:
        raise AnchorError(f"{mutant.file}: {mutant.function}: {mutant.old!r} found {count} times (expected 1)")
    return "".join(lines[:start]) + body.replace(mutant.old, mutant.new) + "".join(lines[end:])


@dataclass
class Outcome:
    mutant: Mutant
    verdict: str  # killed, survived, broken, anchor-lost
    test: str  # the first failing test (killed), else a note
    seconds: float


def run_tests(copy: Path, tests: tuple[str, ...], timeout: float, workers: int = 1) -> tuple[int, str]:
    """pytest -x over ``tests`` in ``copy`` (on ``workers`` xdist workers when more than one)."""
    env = dict(os.environ, PYTHONPATH=str(copy), PYTHONDONTWRITEBYTECODE="1")
    env.pop("WARPIS_TEST_CACHE_DIR", None)  # each run its own theory cache: a mutant's results are its own
    spread = ["-n", str(workers)] if workers > 1 else []
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-rfE", *spread, *tests]
    try:
        proc = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return -1, "timed out"
    return proc.returncode, proc.stdout + proc.stderr


def run_mutant(copy: Path, mutant: Mutant, planted: str, timeout: float) -> Outcome:
    """The mutant's file in ``copy`` replaced by ``planted``, its tests run, the file restored."""
    path = copy / mutant.file
    original = path.read_text()
    path.write_text(planted)
    t0 = time.perf_counter()
    try:
        status, output = run_tests(copy, mutant.tests, timeout)
    finally:
        path.write_text(original)
    return judge(mutant, status, output, time.perf_counter() - t0)


def judge(mutant: Mutant, status: int, output: str, seconds: float) -> Outcome:
    failed = re.findall(r"^FAILED (\S+)", output, re.M)
    errors = re.findall(r"^ERROR (\S+)", output, re.M)
    if status == 1 and failed:
        return Outcome(mutant, "killed", failed[0], seconds)
    if status == 0:
        return Outcome(mutant, "survived", "every selected test passed", seconds)
    note = errors[0] if errors else ("timed out" if status == -1 else f"pytest exit status {status}")
    return Outcome(mutant, "broken", note, seconds)


def make_copy() -> Path:
    copy = Path(tempfile.mkdtemp(prefix="warpis-mutants-"))
    for name in COPIED:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, copy / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        elif src.exists():
            shutil.copy2(src, copy / name)
    return copy


def check_import(copy: Path) -> None:
    """The copy, not an installed warpis, must be the one the tests import."""
    env = dict(os.environ, PYTHONPATH=str(copy))
    where = subprocess.run([sys.executable, "-c", "import warpis; print(warpis.__file__)"], cwd=copy, env=env,
                           capture_output=True, text=True, check=True).stdout.strip()
    if not Path(where).resolve().is_relative_to(copy.resolve()):
        raise SystemExit(f"mutants: the tests would import {where}, not the mutated copy in {copy}")


def markdown(outcomes: list[Outcome], total: float) -> str:
    lines = ["| mutant | bug | verdict | caught by | seconds |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| `{o.mutant.name}` | {o.mutant.bug} | {o.verdict} | `{o.test}` | {o.seconds:.0f} |" for o in outcomes]
    killed = sum(o.verdict == "killed" for o in outcomes)
    lines.append(f"\n{killed} of {len(outcomes)} killed in {total / 60:.1f} minutes.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("names", nargs="*", help="mutants to run (default: all)")
    p.add_argument("--list", action="store_true", help="list the mutants and exit")
    p.add_argument("--markdown", action="store_true", help="print the result table as Markdown")
    p.add_argument("--timeout", type=float, default=900, help="seconds per mutant's test run (default 900)")
    p.add_argument("--no-clean-check", action="store_true",
                   help="skip running the selected tests on the unmutated copy first")
    p.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)),
                   help="mutants run at once, each in its own copy (default: one per core)")
    args = p.parse_args(argv)
    if args.jobs < 1:
        p.error(f"--jobs must be at least 1 (got {args.jobs})")
    if args.list:
        for m in MUTANTS:
            print(f"{m.name:<36} {m.bug}")
        return 0
    unknown = sorted(set(args.names) - {m.name for m in MUTANTS})
    if unknown:
        p.error(f"unknown mutant(s): {', '.join(unknown)}")
    chosen = [m for m in MUTANTS if not args.names or m.name in args.names]
    start = time.perf_counter()
    copies = [make_copy() for _ in range(args.jobs)]
    try:
        for copy in copies:
            check_import(copy)
        outcomes: list[Outcome] = []
        planted = {}
        for m in chosen:  # every anchor first: a lost one fails fast, before minutes of tests
            try:
                planted[m.name] = plant((copies[0] / m.file).read_text(), m)
            except AnchorError as exc:
                outcomes.append(Outcome(m, "anchor-lost", str(exc), 0.0))
        if not args.no_clean_check and planted:
            tests = tuple(dict.fromkeys(t for m in chosen if m.name in planted for t in m.tests))
            status, output = run_tests(copies[0], tests, args.timeout * 2, args.jobs)
            if status != 0:
                print(output[-3000:], file=sys.stderr)
                print(f"mutants: the unmutated copy fails {' '.join(tests)}: fix that first", file=sys.stderr)
                return 1
            print(f"clean copy passes the selected tests ({time.perf_counter() - start:.0f} s)", flush=True)
        free = list(copies)  # a copy is taken by one mutant at a time
        lock = threading.Lock()

        def one(m: Mutant) -> Outcome:
            with lock:
                copy = free.pop()
            try:
                return run_mutant(copy, m, planted[m.name], args.timeout)
            finally:
                with lock:
                    free.append(copy)

        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            for done in as_completed([pool.submit(one, m) for m in chosen if m.name in planted]):
                outcome = done.result()
                outcomes.append(outcome)
                print(f"{outcome.verdict:<9} {outcome.mutant.name:<36} {outcome.test} ({outcome.seconds:.0f} s)",
                      flush=True)
    finally:
        for copy in copies:
            shutil.rmtree(copy, ignore_errors=True)
    total = time.perf_counter() - start
    outcomes.sort(key=lambda o: [m.name for m in MUTANTS].index(o.mutant.name))
    if args.markdown:
        print(markdown(outcomes, total))
    bad = [o for o in outcomes if o.verdict != "killed"]
    for o in bad:
        print(f"mutants: {o.mutant.name}: {o.verdict}: {o.test}", file=sys.stderr)
    print(f"{len(outcomes) - len(bad)} of {len(outcomes)} mutants killed in {total / 60:.1f} min", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
