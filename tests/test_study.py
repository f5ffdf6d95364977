"""Studies: validation before any work, resuming after a kill, figures, recomputing only what changed.

Every study here is tiny (2–4 receivers, N = 4 and 16, 50–100 trials); only the kill test
attaches predictions.  Nothing here is statistical: every number is a deterministic
function of the seed, and the kill lands at a known cell (SIGSTOP from inside, not a race).
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import write_scene

from warpis.runs.study import HEADER, demo_study, load_study

STUDIES = Path(__file__).resolve().parents[1] / "scripts" / "studies"


def write_study(path: Path, **keys) -> Path:
    """A study file whose [study] table holds ``keys`` (TOML literals via repr-like rules)."""
    from conftest import toml_value

    lines = ["[study]"] + [f"{k} = {toml_value(v)}" for k, v in keys.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def tiny(**over) -> dict:
    keys = {"name": "tiny", "seed": 5, "trials": 60, "n": [4, 16], "scenes": ["occluded-quad"],
            "receivers": [0, 1], "estimators": ["independent:single:light-area", "jittered:single:cosine"],
            "predictions": False, "outputs": []}
    keys.update(over)
    return keys


def read_csv(path: Path) -> list[list[str]]:
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


# A study run that stops itself (SIGSTOP) right after results.csv and summary.json have
# been written with exactly K finished cells: warpis.runs.study.write_results, wrapped in
# the child process only (no hook in warpis), so the kill lands at a known point instead of
# racing a polling loop.  argv: K, then the warpis command line.
STOP_AFTER_K_CELLS = """
import os, signal, sys
import warpis.runs.study as study
from warpis.cli import main

K = int(sys.argv[1])
write_results = study.write_results

def stop_after_k(out, s, cells, done, *args, **kwargs):  # done: cell key -> its finished rows
    write_results(out, s, cells, done, *args, **kwargs)
    if len(done) == K:
        os.kill(os.getpid(), signal.SIGSTOP)

study.write_results = stop_after_k
sys.exit(main(sys.argv[2:]))
"""


def _wait_until_stopped(proc: subprocess.Popen, timeout: float, stderr: Path) -> None:
    """Block until ``proc`` is stopped by a signal (it must not exit first)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pid, status = os.waitpid(proc.pid, os.WNOHANG | os.WUNTRACED)
        if pid:
            if not os.WIFSTOPPED(status):  # reaped here: tell Popen, so that nothing signals the pid again
                proc.returncode = os.waitstatus_to_exitcode(status)
                raise AssertionError(f"the study ended (exit {proc.returncode}) instead of stopping after its "
                                     f"cells: {stderr.read_text()}")
            return
        time.sleep(0.05)
    raise AssertionError(f"the study did not stop within {timeout} s")


def without_seconds(rows: list[list[str]]) -> list[list[str]]:
    """Every column but the wall-clock ``seconds`` (the header row included)."""
    i = HEADER.index("seconds")
    return [r[:i] + r[i + 1:] for r in rows]


def test_killed_run_resumes_to_the_same_files(tmp_path, cli):
    """A study process killed (SIGKILL) after exactly K = 2 of its 4 cells — stopped by
    SIGSTOP right after the second cell's files were written, so the point is known, not
    raced — leaves valid files holding exactly those cells; rerunning the same command
    skips exactly those 2 (and says so), computes the other 2, keeps the finished rows
    verbatim (seconds included), and ends with results.csv equal to an uninterrupted run's
    in every column but ``seconds`` and summary.json identical byte for byte.
    Deterministic: no timing, no statistics."""
    k, total = 2, 4
    study = write_study(tmp_path / "study.toml", **tiny(predictions=True, outputs=["calibration"],
                                                         estimators=["independent:single:light-area",
                                                                     "independent:balance:light-area+cosine"]))
    full, cut = tmp_path / "full", tmp_path / "cut"
    with open(tmp_path / "stderr.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", STOP_AFTER_K_CELLS, str(k), "study", str(study), "--out",
                                 str(cut)], stdout=subprocess.DEVNULL, stderr=err)
        try:
            _wait_until_stopped(proc, timeout=240, stderr=tmp_path / "stderr.txt")
            # Stopped: nothing more can be written.  What is on disk now is what a kill leaves.
            killed = read_csv(cut / "results.csv")
            summary_at_kill = load_json(cut / "summary.json")
        finally:
            proc.kill()  # SIGKILL, delivered to a stopped process too
            proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "stderr.txt").read_text()

    assert killed[0] == HEADER
    cells_at_kill = list(dict.fromkeys(r[-1] for r in killed[1:]))
    assert len(cells_at_kill) == k and len(killed) - 1 == 2 * k  # whole cells only: 2 receivers each
    assert summary_at_kill["cells"] == {"total": total, "finished": k} and not summary_at_kill["complete"]

    result = cli("study", study, "--out", cut)
    assert result.status == 0, result.err
    assert f"skipping {k} of {total} cells" in result.out, result.out
    assert f"computed {total - k} cell(s), skipped {k} already finished" in result.out, result.out
    assert "recomputing" not in result.out and "unreadable" not in result.out

    assert cli("study", study, "--out", full).status == 0  # the uninterrupted run
    resumed, reference = read_csv(cut / "results.csv"), read_csv(full / "results.csv")
    assert len(resumed) == 1 + 2 * total and all(r[HEADER.index("pred_exact")] for r in resumed[1:])
    assert resumed[1:1 + 2 * k] == killed[1:]  # the finished cells first (canonical order), verbatim, seconds too
    assert [r[-1] for r in resumed[1:]] == [r[-1] for r in reference[1:]]
    assert without_seconds(resumed) == without_seconds(reference)
    assert (cut / "summary.json").read_bytes() == (full / "summary.json").read_bytes()
    assert (cut / "figures" / "calibration.png").stat().st_size > 1000


def load_json(path: Path) -> dict:
    import json

    return json.loads(path.read_text())


BAD = {
    "unknown key in [study]": (tiny(colour="red"), "unknown key 'colour'"),
    "unknown scene": (tiny(scenes=["occluded-quad", "nowhere/scene.toml"]), "nowhere/scene.toml"),
    "bad estimator": (tiny(estimators=["independent:single:light-area", "jittered:average:cosine"]),
                      "unknown combiner 'average'"),
    "N the pattern cannot take": (tiny(n=[4, 6], estimators=["antithetic:balance:light-area+cosine"]),
                                  "pairs samples"),
    "trials below 4": (tiny(trials=3), "trials must be at least 4"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_study_fails_before_any_work(tmp_path, cli, case):
    """Each bad study file ends with one line naming the study file and the problem, exit status 2,
    and no output directory: the whole file is checked (every scene loaded, every estimator × N)
    before anything runs."""
    keys, words = BAD[case]
    study = write_study(tmp_path / "study.toml", **keys)
    out = tmp_path / "out"
    result = cli("study", study, "--out", out)
    assert result.status == 2
    assert len(result.err_lines) == 1, result.err
    assert result.err_lines[0].startswith(f"warpis: error: {study}: ")
    assert words in result.err_lines[0]
    assert not out.exists()


def test_unknown_key_outside_the_study_table_fails(tmp_path, cli):
    """An unknown top-level table, or a receivers table naming a scene not in the study, is an error too."""
    study = write_study(tmp_path / "study.toml", **tiny())
    study.write_text(study.read_text() + "\n[extra]\nx = 1\n")
    result = cli("study", study, "--out", tmp_path / "out")
    assert result.status == 2 and "unknown key 'extra'" in result.err and len(result.err_lines) == 1
    study = write_study(tmp_path / "study.toml", **tiny(receivers={"two-lights": [0]}))
    result = cli("study", study, "--out", tmp_path / "out")
    assert result.status == 2 and "'two-lights' is not one of the study's scenes" in result.err
    assert not (tmp_path / "out").exists()


def test_figures_of_a_tiny_study_with_a_receiver_grid(tmp_path, cli):
    """Convergence plots per scene × receiver, variance maps per N and the ratio map over a receiver
    grid are written as PNG and PDF (each over 1 kB) and linked from report.md."""
    write_scene(tmp_path / "grid", name="grid-floor",
                receivers={"grid": {"origin": [-1.0, -1.0, 0.0], "edge_u": [2.0, 0.0, 0.0],
                                    "edge_v": [0.0, 2.0, 0.0], "resolution": [2, 2]}})
    study = write_study(tmp_path / "study.toml", **tiny(
        scenes=["grid/scene.toml", "occluded-quad"], receivers={"occluded-quad": [0, 1]}, trials=50,
        outputs=["convergence", "maps", "calibration"]))
    out = tmp_path / "out"
    result = cli("study", study, "--out", out)
    assert result.status == 0, result.err
    stems = [f"convergence-grid-floor-r{r}" for r in range(4)] + ["convergence-occluded-quad-r0",
                                                                  "convergence-occluded-quad-r1",
                                                                  "variance-map-grid-floor-n4",
                                                                  "variance-map-grid-floor-n16",
                                                                  "variance-ratio-grid-floor"]
    report = (out / "report.md").read_text()
    for stem in stems:
        for ext in ("png", "pdf"):
            assert (out / "figures" / f"{stem}.{ext}").stat().st_size > 1000, stem
        assert f"figures/{stem}.png" in report
    assert "## Convergence rates" in report and "## Cells" in report
    summary = load_json(out / "summary.json")
    assert summary["complete"] and summary["scenes"][0]["grid"] == [2, 2]
    assert all(s["slope"] is not None for s in summary["slopes"] if s["scene"] == "grid-floor")


def test_editing_one_estimator_recomputes_only_its_cells(tmp_path, cli):
    """Changing one estimator of the study recomputes that estimator's cells only: the other rows are
    copied verbatim and the replaced estimator's rows are dropped."""
    keys = tiny()
    study = write_study(tmp_path / "study.toml", **keys)
    out = tmp_path / "out"
    assert cli("study", study, "--out", out).status == 0
    first = read_csv(out / "results.csv")
    keys["estimators"] = ["independent:single:light-area", "jittered:single:uniform"]
    write_study(study, **keys)
    result = cli("study", study, "--out", out)
    assert result.status == 0, result.err
    assert "skipping 2 of 4 cells" in result.out and "computed 2 cell(s)" in result.out
    assert "dropping the rows of 2 cell(s)" in result.out
    second = read_csv(out / "results.csv")
    est = HEADER.index("estimator")
    kept = [r for r in first[1:] if r[est] == "independent:single:light-area"]
    assert second[1:5] == kept
    assert [r[est] for r in second[5:]] == ["jittered:single:uniform"] * 4


def test_study_files_validate_and_demo_toml_is_the_demo():
    """Every study in scripts/studies/ passes validation, one per bundled scene, and demo.toml
    gives exactly the cells of the built-in ``warpis demo`` study."""
    import warpis

    names = {p.stem for p in STUDIES.glob("*.toml")}
    assert set(warpis.bundled_scenes()) | {"demo"} <= names
    for path in sorted(STUDIES.glob("*.toml")):
        assert load_study(path).cells()
    assert [c.key for c in load_study(STUDIES / "demo.toml").cells()] == [c.key for c in demo_study().cells()]
    assert load_study(STUDIES / "demo.toml").labels == demo_study().labels
