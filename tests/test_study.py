"""Studies: validation before any work, resuming after a kill, figures, recomputing only what changed.

Every study here is tiny (2–4 receivers, N = 4 and 16, 50–100 trials); only the kill test
attaches predictions, which also makes its cells slow enough to be killed between two.
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


def without_seconds(rows: list[list[str]]) -> list[list[str]]:
    i = HEADER.index("seconds")
    return [r[:i] + r[i + 1:] for r in rows]


def cli_study(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "warpis.cli", "study", *map(str, args)], **kw)


def test_killed_run_resumes_to_the_same_files(tmp_path):
    """A study process killed (SIGKILL) after its first cell leaves valid files holding the finished
    cells; rerunning the same command skips them (and says so), copies their rows verbatim and ends
    with results.csv identical to an uninterrupted run in another directory (byte for byte once the
    wall-clock ``seconds`` column is set aside) and summary.json identical byte for byte."""
    study = write_study(tmp_path / "study.toml", **tiny(predictions=True, outputs=["calibration"],
                                                         estimators=["independent:single:light-area",
                                                                     "independent:balance:light-area+cosine"]))
    full, cut = tmp_path / "full", tmp_path / "cut"
    # The uninterrupted run goes alongside the one to be killed (most of each is start-up).
    ok = cli_study(study, "--out", full, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    proc = cli_study(study, "--out", cut, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    results = cut / "results.csv"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if results.is_file() and len(read_csv(results)) > 1:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the study finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)

    killed = read_csv(results)  # still a valid CSV holding whole cells only
    assert killed[0] == HEADER
    cells = {r[-1] for r in killed[1:]}
    assert len(killed) - 1 == 2 * len(cells) and 1 <= len(cells) < 4
    assert load_json(cut / "summary.json")["cells"]["finished"] in (len(cells) - 1, len(cells))

    again = cli_study(study, "--out", cut, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = again.communicate(timeout=240)
    assert again.returncode == 0, err
    assert f"skipping {len(cells)} of 4 cells" in out
    assert ok.wait(timeout=240) == 0, ok.stderr.read()

    resumed, reference = read_csv(results), read_csv(full / "results.csv")
    assert without_seconds(resumed) == without_seconds(reference)
    assert all(row in resumed for row in killed[1:])  # finished rows kept verbatim, seconds included
    assert (cut / "summary.json").read_bytes() == (full / "summary.json").read_bytes()
    assert len(resumed) == 9 and all(r[HEADER.index("pred_exact")] for r in resumed[1:])
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
