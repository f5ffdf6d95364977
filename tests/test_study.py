"""Studies: validation before any work, resuming after a kill, figures, recomputing only what changed.

Every study here is tiny (2–4 receivers, N = 4 and 16, 50–100 trials); only the kill test
attaches predictions.  Nothing here is statistical: every number is a deterministic
function of the seed, and the kill lands at a known cell (SIGSTOP from inside, not a race).
"""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import write_scene

from warpis.runs.study_file import HEADER, demo_study, load_study

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
    """Every column but those measured with a clock (``seconds``, ``seconds_per_estimate``,
    ``efficiency``), the header row included."""
    timing = {HEADER.index(name) for name in ("seconds", "seconds_per_estimate", "efficiency")}
    return [[x for k, x in enumerate(r) if k not in timing] for r in rows]


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


def test_efficiency_columns_and_report_table(tmp_path, cli):
    """results.csv carries each cell's CPU seconds per estimate (> 0, the same on every row of a
    cell) and efficiency = 1/(variance × seconds_per_estimate) exactly as written; report.md
    has the efficiency table, with the first estimator at 1 relative to itself."""
    study = write_study(tmp_path / "study.toml", **tiny())
    out = tmp_path / "out"
    assert cli("study", study, "--out", out).status == 0
    rows = read_csv(out / "results.csv")
    col = {name: k for k, name in enumerate(rows[0])}
    per_cell: dict[str, set[str]] = {}
    for r in rows[1:]:
        cost, variance, eff = (float(r[col[k]]) for k in ("seconds_per_estimate", "variance", "efficiency"))
        assert 0 < cost < 1.0
        assert eff == 1.0 / (variance * cost)
        per_cell.setdefault(r[col["cell"]], set()).add(r[col["seconds_per_estimate"]])
    assert all(len(costs) == 1 for costs in per_cell.values())
    report = (out / "report.md").read_text()
    table = report.split("## Efficiency", 1)[1].split("##", 1)[0]
    assert "| 4 | `independent:single:light-area` | 1 |" in table
    assert "| 16 | `jittered:single:cosine` |" in table


def _camera_scene(directory: Path, width: int = 16, height: int = 12) -> Path:
    """A lambert floor half shadowed by a phong blocker under a square light, seen from above."""
    from conftest import floor_entry, light_entry, quad

    v, f = quad((0.6, 0.0, 0.5), (0.3, 1.5), "up")
    meshes = [floor_entry(half=1.5, material={"type": "lambert", "albedo": 0.5}),
              light_entry(height=2.0, half=0.3),
              {"path": "blocker.obj", "vertices": v, "faces": f,
               "material": {"type": "phong", "exponent": 20.0, "albedo": 0.5}}]
    camera = {"camera": {"position": [0.0, -0.1, 4.0], "target": [0.0, 0.0, 0.0], "fov": 45.0, "width": width,
                         "height": height}}
    return write_scene(directory, meshes=meshes, receivers=camera, material=None)


def test_study_over_a_camera_scene(tmp_path, cli):
    """A study on a camera scene draws its variance, ratio and slope maps over the image and its
    convergence figures for representative pixels (lit, penumbra, glossy highlight) that are
    what they say: the lit pixel gets all its unoccluded light, the penumbra pixel about half."""
    import warpis
    from warpis.analysis.reference import unoccluded_lambert

    scene_file = _camera_scene(tmp_path / "cam")
    keys = tiny(scenes=["cam/scene.toml"], trials=40, outputs=["convergence", "maps"],
                estimators=["jittered:single:light-area", "jittered:balance:light-area+bsdf"])
    del keys["receivers"]  # every pixel
    study = write_study(tmp_path / "study.toml", **keys)
    out = tmp_path / "out"
    result = cli("study", study, "--out", out)
    assert result.status == 0, result.err
    report = (out / "report.md").read_text()
    for stem in ("variance-map-test-scene-n4", "variance-map-test-scene-n16", "variance-ratio-test-scene",
                 "slope-map-test-scene"):
        assert (out / "figures" / f"{stem}.png").stat().st_size > 1000, stem
        assert f"figures/{stem}.png" in report
    note = next(line for line in report.splitlines() if "representative pixels" in line)
    picked = dict(re.findall(r"(lit|penumbra|glossy highlight): receiver (\d+)", note))
    assert set(picked) == {"lit", "penumbra", "glossy highlight"}
    scene = warpis.load_scene(scene_file)
    refs = {int(r[1]): float(r[8]) for r in read_csv(out / "results.csv")[1:]}
    lit, shade = int(picked["lit"]), int(picked["penumbra"])
    share = np.array([refs[lit], refs[shade]]) / unoccluded_lambert(scene, [lit, shade])
    assert share[0] > 0.999 and 0.2 < share[1] < 0.8
    assert scene.receivers.material_name(int(picked["glossy highlight"])) == "phong"
    assert "rows: see" in report or "## Cells" in report


def test_predictions_at_too_many_camera_pixels_is_one_line(tmp_path, cli):
    """Predictions at every pixel of a camera scene would take hours: refused before any work."""
    _camera_scene(tmp_path / "cam")
    keys = tiny(scenes=["cam/scene.toml"], predictions=True)
    del keys["receivers"]
    study = write_study(tmp_path / "study.toml", **keys)
    out = tmp_path / "out"
    result = cli("study", study, "--out", out)
    assert result.status == 2 and not out.exists()
    assert len(result.err.strip().splitlines()) == 1 and "at most 64" in result.err
