#!/usr/bin/env python
"""Generate the scenes bundled with warpis under ``meshes/<name>/``.

Each scene folder holds a ``scene.toml`` and the mesh files it names. The
generator is deterministic (fixed seeds, fixed float formatting, no
timestamps), so the committed output can be checked against a fresh run::

    python scripts/make_scenes.py            # rewrite meshes/<name>/ and verify
    python scripts/make_scenes.py --check    # exit 1 if the committed files differ

After writing, every scene is read back from disk and verified with trimesh
ray casting: visible fraction of each emitter from each receiver, winding and
orientation of every mesh, emitter facing, and receivers lying on a surface.
The builders and the verification are :mod:`warpis.scenes.builders.mesh_scenes`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpis.scenes.builders.mesh_scenes import check, generate

MESH_ROOT = Path(__file__).resolve().parents[1] / "meshes"


def main(argv: list[str] | None = None) -> int:
    """Generate (or check) the bundled scenes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary folder, exit 1 if meshes/ differs")
    parser.add_argument("--root", type=Path, default=MESH_ROOT, help="scene root folder")
    args = parser.parse_args(argv)
    if args.check:
        return check(args.root)
    generate(args.root)
    print("\nall scenes verified")
    return 0


if __name__ == "__main__":
    sys.exit(main())
