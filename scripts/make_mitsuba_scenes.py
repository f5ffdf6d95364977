#!/usr/bin/env python
"""Generate the Mitsuba 3 scenes bundled with warpis under ``meshes/<name>/``.

Each scene folder holds a Mitsuba 3 ``scene.xml``, the PLY meshes it names and a
``scene.receivers.toml`` sidecar with warpis's receivers.  The generator is
deterministic (fixed float formatting, no timestamps), so the committed output can be
checked against a fresh run::

    python scripts/make_mitsuba_scenes.py                    # rewrite and verify
    python scripts/make_mitsuba_scenes.py --check            # exit 1 if the committed files differ
    python scripts/make_mitsuba_scenes.py --preview /tmp/p   # also render small previews there

After writing, every scene is read back by Mitsuba (``scalar_rgb``) and verified.  The
scenes (``mitsuba-veach-plates``, ``mitsuba-cornell-box``), their builders and the
verification are :mod:`warpis.scenes.builders.mitsuba_scenes`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpis.scenes.builders.mitsuba_scenes import check, generate

MESH_ROOT = Path(__file__).resolve().parents[1] / "meshes"


def main(argv: list[str] | None = None) -> int:
    """Generate (or check) the bundled Mitsuba scenes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary folder, exit 1 if meshes/ differs")
    parser.add_argument("--root", type=Path, default=MESH_ROOT, help="scene root folder")
    parser.add_argument("--preview", type=Path, metavar="DIR",
                        help="also render a 16 spp preview of each scene into DIR")
    args = parser.parse_args(argv)
    if args.check:
        return check(args.root)
    generate(args.root, args.preview)
    print("\nall scenes verified")
    return 0


if __name__ == "__main__":
    sys.exit(main())
