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


# In a fresh process with an empty kernel cache: seed it and load every module; the
# modules whose source Warp had to write (the first step of a compile).
COLD_LOAD = textwrap.dedent("""
    import json
    from pathlib import Path
    import warp as wp
    import warpis
    from warpis.kernels.precompiled import CPU_BLOCK_DIM, MODULES, module_folders, seed_kernel_cache
    seed_kernel_cache()
    cache = Path(wp.config.kernel_cache_dir)
    for name in MODULES:
        wp.load_module(name, device="cpu", block_dim=CPU_BLOCK_DIM)
    compiled = [n for n, f in module_folders().items() if (cache / f / (f + ".cpp")).exists()]
    print(json.dumps({"compiled": compiled}))
""")


def _skip_unless_built_for_here() -> None:
    if shipped_warp() != wp.config.version:
        pytest.skip(f"the shipped objects are for warp-lang {shipped_warp()}, this is {wp.config.version}: "
                    "python scripts/precompile_kernels.py builds them for it")
    if precompiled._manifest().get("target") != precompiled.cpu_target():
        pytest.skip(f"the shipped objects are for {precompiled._manifest().get('target')}, "
                    f"this machine is {precompiled.cpu_target()}")


def test_a_cold_cache_loads_the_shipped_objects_without_compiling(tmp_path):
    """On any CPU of the shipped target (operating system, architecture, Warp's LLVM):
    the objects do not depend on the CPU's instruction-set features."""
    _skip_unless_built_for_here()
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "warp"))
    done = subprocess.run([sys.executable, "-c", COLD_LOAD], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result == {"compiled": []}, "a module compiled although its object was seeded"


def test_the_shipped_objects_are_for_no_particular_cpu():
    """Compiled for the triple's generic CPU: Warp's object names hash no host
    instruction-set features (the manifest's target is this machine's key of the portable
    flags, which holds none), and no module asks for -march=native."""
    _skip_unless_built_for_here()
    suffix = f".cpu{precompiled.cpu_target().rsplit('-', 1)[1]}.o"
    for folder in shipped_folders():
        assert [p.name for p in folder.glob("*.o")] == [folder.name + suffix]
    for name in MODULES:
        assert wp.get_module(name).options["cpu_compiler_flags"] == precompiled.CPU_COMPILER_FLAGS
    assert "-march" not in precompiled.CPU_COMPILER_FLAGS


# manifest text, and whether its folders still count as current content (stale_modules
# judges the content hash, not the Warp version the objects are for).
MANIFESTS = [('{"warp": "0.0.1", "target": "@", "folders": %s}', True), ('{"folders": %s}', True),
             ('{"warp": "' + wp.config.version + '", "target": "1.19.0-Darwin-arm64-0", "folders": %s}', True),
             ('{"warp": "' + wp.config.version + '", "folders": %s}', True), ("not json %s", False), ("[%s]", False)]


@pytest.mark.parametrize("manifest, current", MANIFESTS)
def test_objects_of_another_warp_target_or_a_broken_manifest_are_not_used(tmp_path, monkeypatch, manifest,
                                                                            current):
    folders = json.dumps(sorted(module_folders().values()))
    (tmp_path / "manifest.json").write_text(manifest.replace("@", precompiled.cpu_target()) % folders)
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


def test_a_warp_without_a_cpu_compiler_uses_no_shipped_object(monkeypatch):
    def no_llvm(**_):
        raise RuntimeError("Cannot identify the CPU cache target because the LLVM backend is unavailable.")

    monkeypatch.setattr(wp, "get_cpu_kernel_cache_key", no_llvm)
    assert precompiled.cpu_target() is None
    assert shipped_folders() == []
