#!/usr/bin/env python
"""Compile warpis's built-in kernel modules ahead of time into ``warpis/kernels/precompiled/``.

Run it after changing any kernel or ``@wp.func`` (or after moving to another warp-lang)
and commit the result: ``tests/test_precompiled.py`` fails while a shipped object is
stale.  Each module is loaded on the CPU with ``wp.load_module`` into an empty kernel
cache, with the modules' own portable flags (``CPU_COMPILER_FLAGS``), exactly as a launch
loads it; the object and its metadata are kept, and the manifest names the target they
are for (the operating system, the architecture, Warp's LLVM).
:mod:`warpis.kernels.precompiled` says how they are found, and where not.

    python scripts/precompile_kernels.py           # rebuild every module (about a minute)
    python scripts/precompile_kernels.py --check   # exit 1 naming the stale modules
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

# An empty kernel cache of this run's own: what it compiles is what it keeps.
BUILD_CACHE = tempfile.mkdtemp(prefix="warpis-precompile-")
os.environ["WARP_CACHE_PATH"] = BUILD_CACHE

import warp as wp

import warpis  # noqa: F401  (imports every kernel module, whose content is hashed)
from warpis.kernels.precompiled import CPU_BLOCK_DIM, MANIFEST, SHIPPED, cpu_target, module_folders, stale_modules


def build() -> None:
    """Replace the shipped folders with one object and its metadata per module."""
    wp.init()
    folders = module_folders()
    target = cpu_target()
    if target is None:
        sys.exit("this Warp has no CPU compiler: nothing to precompile")
    suffix = f".cpu{target.rsplit('-', 1)[1]}.o"  # Warp's object name ends with the target's hash
    for old in SHIPPED.glob("wp_*"):
        shutil.rmtree(old)
    SHIPPED.mkdir(exist_ok=True)
    for name, folder in folders.items():
        wp.load_module(name, device="cpu", block_dim=CPU_BLOCK_DIM)
        built = Path(wp.config.kernel_cache_dir) / folder
        kept = [f for f in built.iterdir() if f.suffix in (".o", ".meta")]
        if len(kept) != 2 or not any(f.name.endswith(suffix) for f in kept):
            sys.exit(f"{name}: expected one object (*{suffix}) and its metadata in {built}, "
                     f"found {sorted(os.listdir(built))}")
        (SHIPPED / folder).mkdir()
        for f in kept:
            shutil.copyfile(f, SHIPPED / folder / f.name)
        print(f"{name}: {folder}")
    manifest = {"warp": wp.config.version, "target": target, "folders": sorted(folders.values())}
    MANIFEST.write_text(json.dumps(manifest, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a shipped object is stale")
    args = parser.parse_args(argv)
    wp.config.quiet = True
    try:
        if args.check:
            stale = stale_modules()
            if stale:
                print(f"stale (run python scripts/precompile_kernels.py): {', '.join(stale)}", file=sys.stderr)
            return 1 if stale else 0
        build()
        return 0
    finally:
        shutil.rmtree(BUILD_CACHE, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
