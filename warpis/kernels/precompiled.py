"""warpis's built-in kernels, compiled ahead of time and shipped with the package.

Warp compiles a module the first time one of its kernels launches (the trial kernel's
module alone takes 20–50 s on two cores) and keeps the object in its kernel cache.
``scripts/precompile_kernels.py`` builds the modules named in :data:`MODULES` ahead of
time (``wp.load_module`` into an empty kernel cache, as a CPU launch loads them) and keeps
each object and its metadata in ``warpis/kernels/precompiled/``;
:func:`seed_kernel_cache` copies them into Warp's kernel cache before the first launch
(``device.upload`` and ``camera.first_hits``, the two ways into these modules), where
Warp's own lookup finds them.  Nothing else changes: the launch, the flags, the results.

Warp names each object by the module's content hash (the source of every kernel and
function it reaches, and the compile options) and by a hash of the LLVM version, the
target triple and, under Warp's default ``-march=native``, the host CPU's instruction-set
features.  Under ``-march=native`` a shipped object would be found only on a CPU with the
very features of the machine that built it, which is hardly any user's.  So these
modules compile with :data:`CPU_COMPILER_FLAGS` (:func:`compile_portably`): Warp's
default flags less ``-march=native``, the generic CPU of the triple.  Their objects are
then found by the very code they were built from on every machine of the same operating
system and architecture (the manifest's ``target``, :func:`cpu_target`); elsewhere Warp
compiles as it always does.  The generic target costs the trial kernels nothing
measurable and changes no result (docs/development.md, "Kernels shipped compiled").  The
Warp version is checked too, because the objects of one version are not those of
another and Warp keeps a cache folder per version.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import threading
from pathlib import Path

import warp as wp

from .. import files

# The modules whose kernels warpis launches (user techniques and patterns build their own).
MODULES = (
    "warpis.kernels.estimators",
    "warpis.kernels.evaluate",
    "warpis.kernels.techniques",
    "warpis.kernels.device",
    "warpis.kernels.integrand",
    "warpis.kernels.camera",
)
# Warp's cpu_compiler_flags less -march=native: Warp's own tuning (its default raises the
# inlining thresholds), for the generic CPU of the target triple, so that Warp's object
# name carries no host instruction-set features.  Derived, not copied, so that it follows
# Warp's defaults to the next release (whose objects precompile_kernels.py rebuilds).
CPU_COMPILER_FLAGS = " ".join(flag for flag in (wp.config.cpu_compiler_flags or "").split() if flag != "-march=native")
# A CPU launch loads a module for block_dim 1, which is part of its content hash; Warp's
# compile_aot_module builds for the module's block_dim option (256) instead, which no
# CPU launch would find.
CPU_BLOCK_DIM = 1
SHIPPED = Path(__file__).resolve().parent / "precompiled"
MANIFEST = SHIPPED / "manifest.json"

_seeded = False
_seed_lock = threading.Lock()


def seed_kernel_cache() -> None:
    """Copy the shipped objects into Warp's kernel cache (once per process; a copy that
    is already there is left alone).  Starts Warp if it has not started."""
    global _seeded
    with _seed_lock:
        if _seeded:
            return
        _seeded = True
        wp.init()
        shipped = shipped_folders()
        if not shipped or wp.config.kernel_cache_dir is None:
            return
        cache = Path(wp.config.kernel_cache_dir)
        for folder in shipped:
            try:
                _copy_missing(folder, cache / folder.name)
            except OSError:  # a read-only or full cache: Warp compiles, as without this
                return


def compile_portably(module: str | wp.Module) -> None:
    """Compile ``module`` (a module name, or a ``wp.Module``) with :data:`CPU_COMPILER_FLAGS`:
    every module of :data:`MODULES` calls it on itself, and the kernels rebuilt around
    user code take it too, so that machines of different CPUs sharing one kernel cache (a
    cluster's shared home folder) compile them once between them."""
    wp.set_module_options({"cpu_compiler_flags": CPU_COMPILER_FLAGS}, module)


def cpu_target() -> str | None:
    """This machine's key for objects compiled with :data:`CPU_COMPILER_FLAGS`: Warp's
    version, the operating system, the architecture and a hash of the LLVM version and
    target triple (``wp.get_cpu_kernel_cache_key``); None where Warp has no CPU compiler.
    Starts Warp."""
    try:
        return wp.get_cpu_kernel_cache_key(cpu_compiler_flags=CPU_COMPILER_FLAGS)
    except RuntimeError:  # no LLVM backend: no CPU kernels to find objects for
        return None


def shipped_warp() -> str | None:
    """The warp-lang version the shipped objects were built with (None: no usable manifest)."""
    return _manifest().get("warp")


def shipped_folders(any_warp: bool = False) -> list[Path]:
    """The shipped module folders usable here: none where this Warp's version or this
    machine's :func:`cpu_target` differs from the one they were built for, unless
    ``any_warp`` (their content, not their use)."""
    manifest = _manifest()
    if not any_warp and (manifest.get("warp") != wp.config.version or manifest.get("target") != cpu_target()):
        return []
    return [SHIPPED / name for name in manifest.get("folders", []) if (SHIPPED / name).is_dir()]


def _manifest() -> dict:
    try:
        manifest = json.loads(MANIFEST.read_text())
    except (OSError, ValueError):
        return {}
    return manifest if isinstance(manifest, dict) else {}


def module_folders() -> dict[str, str]:
    """Each of :data:`MODULES` → the cache folder Warp names by its current content, as a
    CPU launch loads it (``wp_<module>_<hash>``).  Hashing compiles nothing.  The modules
    must have been imported (``import warpis`` imports them all): this floor does not
    reach up for the analysis module."""
    missing = [name for name in MODULES if name not in sys.modules]
    if missing:
        raise RuntimeError(f"import warpis before hashing its kernel modules (not imported: {', '.join(missing)})")
    return {name: wp.get_module(name).get_module_identifier(block_dim=CPU_BLOCK_DIM) for name in MODULES}


def stale_modules() -> list[str]:
    """The modules of :data:`MODULES` whose current content has no shipped object
    (``python scripts/precompile_kernels.py`` builds them).  Judged by the content hash
    alone: a Warp release other than the objects' own leaves them unused, not stale."""
    shipped = {folder.name for folder in shipped_folders(any_warp=True) if any(folder.glob("*.o"))}
    return [name for name, folder in module_folders().items() if folder not in shipped]


def _copy_missing(source: Path, target: Path) -> None:
    """Copy each file of ``source`` that ``target`` lacks, the metadata before the object,
    each through a temporary name and a rename, so that a process that looks at the same
    moment sees a whole file or none."""
    target.mkdir(parents=True, exist_ok=True)
    for name in sorted(os.listdir(source), key=lambda n: not n.endswith(".meta")):
        if (target / name).exists():
            continue
        with open(source / name, "rb") as src, files.replacing(target / name, durable=False) as fh:
            shutil.copyfileobj(src, fh)
