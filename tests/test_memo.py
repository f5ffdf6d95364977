"""Theory results kept on disk (``warpis.analysis.memo``): a kept result is the computed one
bit for bit, and any input it depends on is part of its name, so none is ever stale."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

import warpis
from warpis.analysis import memo, quadrature
from warpis.vocabulary import UserEntry


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPIS_CACHE_DIR", str(tmp_path))
    return tmp_path / "theory"


def no_computing(*args, **kwargs):
    raise AssertionError("computed although the result was kept")


def test_kept_moments_are_the_computed_ones_and_are_not_computed_again(cache, monkeypatch):
    scene = warpis.load_scene("occluded-quad")
    techniques = ("light-area", "cosine")
    fresh = quadrature._moments(scene, 2, techniques, 64, quadrature.SEED)
    first = quadrature.moments(scene, 2, techniques, sub=64)
    assert first == fresh and len(list(cache.glob("*/moments-*.json"))) == 1
    monkeypatch.setattr(quadrature, "_moments", no_computing)
    assert quadrature.moments(scene, 2, techniques, sub=64) == fresh  # Estimate's == compares floats exactly
    with pytest.raises(AssertionError, match="computed although"):
        quadrature.moments(scene, 3, techniques, sub=64)  # another receiver is another result


def test_a_kept_variance_survives_the_process_bit_for_bit(cache):
    """A second process reads what the first computed: the same digits, without the quadrature."""
    code = textwrap.dedent("""
        import sys, warpis
        from warpis.analysis import quadrature
        if sys.argv[1] == "again":
            def refuse(*args, **kwargs):
                raise SystemExit("computed although the result was kept")
            quadrature.block_variance = refuse
        v = quadrature.exact_variance(warpis.load_scene("occluded-quad"), 1, "jittered:power:light-area+cosine", 8)
        print(repr((v.value, v.stderr, v.points)))
    """)
    env = {**os.environ, "WARPIS_CACHE_DIR": str(cache.parent)}
    runs = [subprocess.run([sys.executable, "-c", code, when], capture_output=True, text=True, env=env)
            for when in ("first", "again")]
    assert [r.returncode for r in runs] == [0, 0], runs[1].stderr[-2000:]
    assert runs[0].stdout.splitlines()[-1] == runs[1].stdout.splitlines()[-1]
    assert len(list(cache.glob("*/variance-*.json"))) == 1


def test_every_input_is_part_of_the_name(cache, monkeypatch, tmp_path):
    base = memo.kept_path("variance", "digest", "cpu", (1, "jittered", 0.1))
    assert base.parent == cache / memo.code_digest()[:16]
    others = {memo.kept_path("moments", "digest", "cpu", (1, "jittered", 0.1)),
              memo.kept_path("variance", "other", "cpu", (1, "jittered", 0.1)),
              memo.kept_path("variance", "digest", "cuda:0", (1, "jittered", 0.1)),
              memo.kept_path("variance", "digest", "cpu", (2, "jittered", 0.1)),
              memo.kept_path("variance", "digest", "cpu", (1, "jittered", 0.1 + 1e-16))}
    assert base not in others and len(others) == 5
    # The code: any source file of the package changes the name of every result.
    package = tmp_path / "package"
    (package / "sub").mkdir(parents=True)
    (package / "a.py").write_text("A = 1\n")
    (package / "sub" / "b.py").write_text("B = 2\n")
    monkeypatch.setattr(memo, "PACKAGE", package)
    memo.code_digest.cache_clear()
    try:
        before = memo.kept_path("variance", "digest", "cpu", ())
        (package / "sub" / "b.py").write_text("B = 3\n")
        memo.code_digest.cache_clear()
        after = memo.kept_path("variance", "digest", "cpu", ())
        assert after != before and after.parent != before.parent  # another code version's folder
    finally:
        memo.code_digest.cache_clear()


def test_only_the_last_few_code_versions_keep_their_results(cache, monkeypatch):
    """Each code version keeps its results in its own folder; the first use of one by a
    process removes all but the KEEP_CODES most recently used, never its own, and the
    flat files of the earlier layout, and leaves what is not a result alone."""
    cache.mkdir()
    (cache / "variance-0123.json").write_text("[1.0, 0.0, 0]")  # the flat layout
    (cache / "notes.txt").write_text("not warpis's")
    for age, code in enumerate("abcdef"):  # six older versions, "a" the most recently used
        folder = cache / (code * 16)
        folder.mkdir()
        (folder / "moments-1.json").write_text("{}")
        os.utime(folder, (1e9 - age, 1e9 - age))
    memo.code_folder.cache_clear()
    path = memo.kept_path("variance", "digest", "cpu", ())
    left = sorted(p.name for p in cache.iterdir())
    assert left == sorted([path.parent.name, "a" * 16, "b" * 16, "c" * 16, "notes.txt"])
    assert len(left) - 1 == memo.KEEP_CODES
    # The first use marks the folder used: a newer version now keeps it among the last few.
    monkeypatch.setattr(memo, "code_digest", lambda: "f" * 64)
    memo.code_folder.cache_clear()
    memo.kept_path("variance", "digest", "cpu", ())
    assert path.parent.is_dir() and not (cache / ("c" * 16)).exists()
    memo.code_folder.cache_clear()


def test_a_broken_or_foreign_file_is_computed_again_and_replaced(cache):
    path = memo.kept_path("variance", "digest", "cpu", (7,))
    assert path.parent.is_dir()  # the code version's folder, made when first named
    calls = []

    def compute() -> quadrature.Estimate:
        calls.append(1)
        return quadrature.Estimate(0.1, 1e-3, 64)

    for content in ("{not json", "[1, 2]", '{"value": 1}', ""):
        path.write_text(content)
        got = memo.kept(path, compute, quadrature._estimate_json, quadrature._estimate_of)
        assert got == quadrature.Estimate(0.1, 1e-3, 64)
        assert json.loads(path.read_text()) == [0.1, 1e-3, 64]
    assert len(calls) == 4


def test_an_unwritable_cache_only_costs_the_next_computation(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("WARPIS_CACHE_DIR", str(blocker))
    path = memo.kept_path("variance", "digest", "cpu", ())
    assert memo.kept(path, lambda: quadrature.Estimate(1.0, 0.0), quadrature._estimate_json,
                     quadrature._estimate_of) == quadrature.Estimate(1.0, 0.0)
    assert blocker.read_text().startswith("a file")


def test_what_registered_python_computes_is_never_kept(cache, monkeypatch):
    """A user technique's or pattern's code is outside the package's digest: its results
    are computed every time, never read back."""
    assert memo.keepable(("light-area", "cosine"), "jittered")
    monkeypatch.setattr(memo, "user_techniques", lambda: (UserEntry("mine", 99, ()),))
    monkeypatch.setattr(memo, "user_patterns", lambda: (UserEntry("my-grid", 98, ()),))
    assert not memo.keepable(("light-area", "mine"))
    assert not memo.keepable(("light-area", "cosine"), "my-grid")
    assert memo.keepable(("light-area", "cosine"), "jittered")
    monkeypatch.setattr(quadrature.memo, "keepable", lambda *args: False)
    scene = warpis.load_scene("occluded-quad")
    quadrature.moments(scene, 2, ("light-area",), sub=32)
    assert not cache.exists()


def test_a_second_combiner_reads_the_first_ones_evaluations(monkeypatch):
    """Balance and power over one set at one layout evaluate the same points: the second
    reuses the first's values (quadrature._recent_values) and gets what it would compute."""
    from warpis.kernels.estimators import parse_estimator
    from warpis.kernels.patterns import PATTERNS

    scene = warpis.load_scene("occluded-quad")
    blocks = PATTERNS["jittered"].blocks(8)
    balance, power = (parse_estimator(f"jittered:{c}:light-area+cosine") for c in ("balance", "power"))
    calls = []
    real = quadrature.Evaluator.__call__
    monkeypatch.setattr(quadrature.Evaluator, "__call__", lambda self, *a, **k: calls.append(1) or real(self, *a, **k))
    quadrature._recent.clear()
    quadrature.block_variance(scene, 2, balance, blocks)
    before = len(calls)
    shared = quadrature.block_variance(scene, 2, power, blocks)
    reused = len(calls) - before
    monkeypatch.setattr(quadrature, "RECENT_EVALUATIONS", 0)
    quadrature._recent.clear()
    before = len(calls)
    fresh = quadrature.block_variance(scene, 2, power, blocks)
    assert reused < len(calls) - before  # at least the first density came from the balance run
    assert shared == fresh  # the same digits


def _counting_evaluations(monkeypatch) -> list[tuple[tuple[str, ...], int]]:
    """(technique set, k) of every evaluation of quadrature.evaluate from here on."""
    calls = []
    real = quadrature.evaluate
    monkeypatch.setattr(quadrature, "evaluate",
                        lambda scene, r, techniques, k, u: calls.append((techniques, k)) or real(scene, r, techniques, k, u))
    return calls


def test_moments_of_several_sets_are_each_ones_own_with_one_evaluation_per_technique(cache, monkeypatch):
    """Every set's moments at a receiver sit at the same points: moments_together evaluates
    each technique of the union once and gives each set, in its own technique order, the
    digits its own computation gives; they are kept per set and read back."""
    scene = warpis.load_scene("occluded-quad")
    sets = [("cosine", "light-area"), ("uniform",), ("light-area",), ("light-area", "cosine")]
    own = [quadrature._moments(scene, 2, s, 32, quadrature.SEED) for s in sets]  # receiver 2: a penumbra
    assert all(m.I.value > 0 and m.E_is2[0].value > 0 for m in own)
    quadrature.upload(scene).cached("int_f2", dict).clear()  # ∫ f² too from the union's light-area
    calls = _counting_evaluations(monkeypatch)
    together = quadrature.moments_together(scene, 2, sets, sub=32)
    assert together == own  # Estimate's == compares floats exactly
    assert sorted(calls) == [(("cosine", "light-area", "uniform"), k) for k in range(3)]
    assert len(list(cache.glob("*/moments-*.json"))) == len(sets)
    calls.clear()
    assert quadrature.moments_together(scene, 2, sets[::-1], sub=32) == own[::-1] and not calls
    assert quadrature.moments(scene, 2, sets[1], sub=32) == own[1] and not calls


def test_a_run_finds_the_moments_of_its_technique_sets_together(cache, monkeypatch):
    """A runner that names its cells' technique sets gets them all at a receiver's first
    ask, each technique evaluated once; a set the scene has no lights for is left to its
    own cell's error."""
    from warpis.kernels.estimators import parse_estimator
    from warpis.runs.cell import MIN_TRIALS, CellJob, RunCache

    scene = warpis.load_scene("occluded-quad")
    run = RunCache()
    run.expect([CellJob(scene, (2,), parse_estimator(spec), 4, MIN_TRIALS, 0)
                for spec in ("independent:single:light-area", "independent:balance:light-area+cosine",
                             "independent:single:envmap")]
               + [CellJob(scene, (5,), parse_estimator("independent:single:cosine"), 4, MIN_TRIALS, 0)])
    assert run.technique_sets == {(scene.digest, 2): [("light-area",), ("light-area", "cosine")],  # not envmap
                                  (scene.digest, 5): [("cosine",)]}  # only where its cell asks
    calls = _counting_evaluations(monkeypatch)
    first = run.moments_of(scene, 2, ("light-area",))
    assert sorted(calls) == [(("light-area", "cosine"), 0), (("light-area", "cosine"), 1)]
    calls.clear()
    both = run.moments_of(scene, 2, ("light-area", "cosine"))
    assert not calls
    quadrature.upload(scene).cached("int_f2", dict).clear()
    monkeypatch.setenv("WARPIS_CACHE_DIR", str(cache.parent / "elsewhere"))  # nothing kept: compute each alone
    assert [first, both] == [quadrature.moments(scene, 2, s) for s in (("light-area",), ("light-area", "cosine"))]
    assert len(calls) == 1 + 2  # each set alone (∫ f² from the first one's light-area)
