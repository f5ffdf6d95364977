"""The kernels shipped precompiled (warpis/kernels/precompiled.py): current, found by a
cold cache without compiling, and ignored where they do not belong."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import warp as wp

from warpis.kernels import precompiled
from warpis.kernels.precompiled import MODULES, module_folders, shipped_folders, shipped_warp, stale_modules


def test_every_shipped_object_is_current():
    assert stale_modules() == [], "run python scripts/precompile_kernels.py and commit warpis/kernels/precompiled/"
    assert {f.name for f in shipped_folders()} == set(module_folders().values())


# In a fresh process with an empty kernel cache: seed it, load the smallest module (which
# tells whether this CPU is the one the objects were built for), then every module.
COLD_LOAD = textwrap.dedent("""
    import json, os, sys
    from pathlib import Path
    import warp as wp
    import warpis
    from warpis.kernels.precompiled import CPU_BLOCK_DIM, MODULES, module_folders, seed_kernel_cache, shipped_folders
    seed_kernel_cache()
    cache = Path(wp.config.kernel_cache_dir)
    folders = module_folders()
    def objects(folder):
        return sorted(p.name for p in folder.glob("*.o"))
    wp.load_module("warpis.kernels.camera", device="cpu", block_dim=CPU_BLOCK_DIM)
    probe = folders["warpis.kernels.camera"]
    shipped = {f.name: objects(f) for f in shipped_folders()}
    if (cache / probe / (probe + ".cpp")).exists():
        print(json.dumps({"other_cpu": objects(cache / probe) != shipped[probe]}))
        sys.exit(0)
    for name in MODULES:
        wp.load_module(name, device="cpu", block_dim=CPU_BLOCK_DIM)
    compiled = [n for n, f in folders.items() if (cache / f / (f + ".cpp")).exists()]
    print(json.dumps({"compiled": compiled}))
""")


def test_a_cold_cache_loads_the_shipped_objects_without_compiling(tmp_path):
    if shipped_warp() != wp.config.version:
        pytest.skip(f"the shipped objects are for warp-lang {shipped_warp()}, this is {wp.config.version}: "
                    "python scripts/precompile_kernels.py builds them for it")
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "warp"))
    done = subprocess.run([sys.executable, "-c", COLD_LOAD], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if result.get("other_cpu"):
        pytest.skip("this CPU's instruction-set features differ from those the shipped objects were built for")
    assert result == {"compiled": []}, "a module compiled although its object was seeded"


# manifest text, and whether its folders still count as current content (stale_modules
# judges the content hash, not the Warp version the objects are for).
MANIFESTS = [('{"warp": "0.0.1", "folders": %s}', True), ('{"folders": %s}', True), ("not json %s", False),
             ("[%s]", False)]


@pytest.mark.parametrize("manifest, current", MANIFESTS)
def test_objects_of_another_warp_version_or_a_broken_manifest_are_not_used(tmp_path, monkeypatch, manifest,
                                                                            current):
    folders = json.dumps(sorted(module_folders().values()))
    (tmp_path / "manifest.json").write_text(manifest % folders)
    for name in module_folders().values():
        (tmp_path / name).mkdir()
        (tmp_path / name / f"{name}.cpu0.o").write_bytes(b"object")
    monkeypatch.setattr(precompiled, "SHIPPED", tmp_path)
    monkeypatch.setattr(precompiled, "MANIFEST", tmp_path / "manifest.json")
    assert shipped_folders() == []
    assert sorted(stale_modules()) == ([] if current else sorted(MODULES))


def test_seeding_copies_only_what_the_cache_lacks(tmp_path):
    source = tmp_path / "shipped" / "wp_m_0000000"
    source.mkdir(parents=True)
    (source / "wp_m_0000000.meta").write_text("meta")
    (source / "wp_m_0000000.cpu1.o").write_bytes(b"object")
    target = tmp_path / "cache" / "wp_m_0000000"
    target.mkdir(parents=True)
    (target / "wp_m_0000000.meta").write_text("kept")
    precompiled._copy_missing(source, target)
    assert (target / "wp_m_0000000.meta").read_text() == "kept"
    assert (target / "wp_m_0000000.cpu1.o").read_bytes() == b"object"
    assert sorted(p.name for p in Path(target).iterdir()) == ["wp_m_0000000.cpu1.o", "wp_m_0000000.meta"]
