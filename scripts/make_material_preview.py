#!/usr/bin/env python
"""Generate the bundled ``mitsuba-material-preview`` scene under ``meshes/``.

Two glossy spheres (a gold ``roughconductor``, a blue ``roughplastic``) on one
smooth-normal mesh, over a checkerboard floor, under a procedural HDR sky with a sun;
the receivers are camera hits (finding them needs Mitsuba).  Deterministic: the same
files on every run (``--check`` exits 1 if the committed ones differ).  The scene's
pieces are :mod:`warpis.scenes.builders.material_preview`.

    python scripts/make_material_preview.py           # write meshes/mitsuba-material-preview
    python scripts/make_material_preview.py --check
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpis.scenes.builders.material_preview import NAME, check, write

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the committed files differ from a fresh run")
    args = parser.parse_args(argv)
    target = ROOT / "meshes" / NAME
    if args.check:
        return check(target)
    write(target)
    print(f"wrote {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
