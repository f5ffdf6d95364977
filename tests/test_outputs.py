"""Output folders of study, demo and verify --out under hostile conditions.

Two runs on one folder, a folder that cannot be written, a full disk, a damaged
results.csv, a run stopped while it draws figures, scene names that are not file names,
and counts the kernels cannot hold.  Each ends in one line on stderr and exit status 2
(or, for damage, a note and a clean resume), with no temporary files left and no
finished row lost.  Studies are tiny: occluded-quad, trials 8, N = 4, two receivers.
"""

from __future__ import annotations

import errno
import functools
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import write_scene
from test_study import read_csv, without_seconds, write_study

from warpis import plots
from warpis.runs import outdir
from warpis.runs.study_file import HEADER

ESTIMATORS = ["independent:single:light-area", "jittered:single:cosine"]
VERIFY = ["verify", "occluded-quad", "--estimators", ESTIMATORS[0], "--n", "4", "--trials", "8",
          "--receivers", "0"]


def small(**over) -> dict:
    keys = {"name": "small", "seed": 3, "trials": 8, "n": [4], "scenes": ["occluded-quad"], "receivers": [0, 1],
            "estimators": list(ESTIMATORS), "predictions": False, "outputs": []}
    keys.update(over)
    return keys


def leftovers(out: Path) -> list[Path]:
    """Temporary files of any warpis writer under ``out``."""
    return [p for p in out.rglob("*") if p.name.endswith((outdir.TMP_SUFFIX, ".tmp"))]


def one_error(result, *words: str) -> str:
    """The run failed with status 2 and exactly one ``warpis: error:`` line holding ``words``."""
    assert result.status == 2, (result.out, result.err)
    assert len(result.err_lines) == 1, result.err
    line = result.err_lines[0]
    assert line.startswith("warpis: error: ") and "Traceback" not in result.err
    for w in words:
        assert w in line, line
    return line


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> tuple[Path, Path]:
    """(study file, output folder) of one uninterrupted run of ``small()``, shared read-only."""
    from warpis.cli import main

    base = tmp_path_factory.mktemp("finished")
    study = write_study(base / "study.toml", **small())
    out = base / "out"
    assert main(["study", str(study), "--out", str(out)]) == 0
    return study, out


def copy_of(finished: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    study, out = finished
    shutil.copytree(out, tmp_path / "out")
    return study, tmp_path / "out"


# --------------------------------------------------------------------------- one run per folder

HOLD = ("import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "os.write(fd, str(os.getpid()).encode())\n"
        "print('held', flush=True)\n"
        "time.sleep(120)\n")


@pytest.mark.parametrize("command", ["study", "verify"])
def test_a_folder_in_use_fails_at_once_naming_the_holder(tmp_path, cli, command):
    """While another process holds OUT/.lock, study and verify --out on OUT stop at once with one
    line naming the holder's PID, and write nothing there."""
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out / ".lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        study = write_study(tmp_path / "study.toml", **small())
        args = ["study", study, "--out", out] if command == "study" else [*VERIFY, "--out", out]
        one_error(cli(*args), f"{out}: in use by another warpis run (pid {holder.pid})")
        assert sorted(p.name for p in out.iterdir()) == [".lock"]
    finally:
        holder.kill()
        holder.wait()


def test_two_processes_on_one_folder_lose_no_rows(tmp_path):
    """Two `warpis study` processes started together on one folder: one runs, the other fails with
    the one-line lock error or (if it came second) resumes; either way no traceback, every row
    present, no temporary file left.  (24 cells: enough writes that unlocked runs collided every time.)"""
    study = write_study(tmp_path / "study.toml", **small(n=list(range(4, 52, 4))))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "warpis.cli", "study", str(study), "--out", str(out)]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=240), *p.communicate()) for p in procs]
    assert 0 in [status for status, _, _ in results]
    for status, _, err in results:
        assert "Traceback" not in err
        if status != 0:
            assert status == 2 and re.fullmatch(r"warpis: error: .*: in use by another warpis run \(pid \d+\).*\n",
                                                err), err
    assert len(read_csv(out / "results.csv")) == 1 + 48 and not leftovers(out)


def test_a_stale_lock_and_stale_temporary_files_do_not_block(tmp_path, cli):
    """A .lock left by a dead process (its PID inside, no flock held) does not block; temporary files
    of a run killed mid-write are swept away."""
    out = tmp_path / "out"
    out.mkdir()
    (out / ".lock").write_text("999999\n")
    for name in (".results.csv.x1y2.warpis-tmp", "results.csv.tmp", "summary.json.tmp"):
        (out / name).write_text("half")
    study = write_study(tmp_path / "study.toml", **small())
    assert cli("study", study, "--out", out).status == 0
    assert not leftovers(out) and len(read_csv(out / "results.csv")) == 5


# --------------------------------------------------------------------------- unwritable output

UNWRITABLE = {
    "under /proc": (lambda tmp: "/proc/warpis-out", "/proc/warpis-out: cannot write: No such file or directory"),
    "under a regular file": (lambda tmp: tmp / "afile" / "sub", "afile/sub: cannot write: Not a directory"),
    "empty --out": (lambda tmp: "", "--out: must name a directory"),
    "a regular file": (lambda tmp: tmp / "afile", "must be a directory"),
}


@pytest.mark.parametrize("command", ["study", "demo", "verify"])
@pytest.mark.parametrize("case", list(UNWRITABLE))
def test_unwritable_output_is_one_line(tmp_path, cli, command, case):
    """An --out that cannot be written (or is empty) ends in one line and status 2 before any work."""
    (tmp_path / "afile").write_text("not a folder")
    make, words = UNWRITABLE[case]
    out = make(tmp_path)
    study = write_study(tmp_path / "study.toml", **small())
    args = {"study": ["study", study], "demo": ["demo"], "verify": VERIFY}[command]
    one_error(cli(*args, "--out", out), words)
    assert (tmp_path / "afile").read_text() == "not a folder"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "study.toml"]


def full_disk(monkeypatch, after: int) -> None:
    """Text writes succeed ``after`` times, then fail as on a full filesystem (half the data written)."""
    real = outdir._write
    calls = {"n": 0}

    def write(fh, data: bytes) -> None:
        calls["n"] += 1
        if calls["n"] > after:
            fh.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fh, data)

    monkeypatch.setattr(outdir, "_write", write)


# Writes of small() with outputs = []: results.csv + summary.json up front, again after each of the
# two cells, then report.md.
FULL_DISK = {
    "first write of a new folder": (0, "results.csv"),
    "after the first cell": (4, "results.csv"),
    "the report": (6, "report.md"),
}


@pytest.mark.parametrize("case", list(FULL_DISK))
def test_full_disk_keeps_what_is_there_and_resumes(tmp_path, cli, monkeypatch, finished, case):
    """A full disk at any write: one line naming the file, no temporary file, the results.csv on disk
    untouched (whole cells only), and a rerun resumes to the uninterrupted run's rows."""
    after, file = FULL_DISK[case]
    study = finished[0]
    out = tmp_path / "out"
    full_disk(monkeypatch, after)
    one_error(cli("study", study, "--out", out), f"{out / file}: cannot write: No space left on device")
    monkeypatch.undo()
    if after == 0:
        assert not out.exists()  # the folder it made held nothing but its lock
    else:
        assert not leftovers(out)
        kept = read_csv(out / "results.csv")
        assert len(kept) - 1 == {4: 2, 6: 4}[after]
    result = cli("study", study, "--out", out)
    assert result.status == 0, result.err
    assert without_seconds(read_csv(out / "results.csv")) == without_seconds(read_csv(finished[1] / "results.csv"))
    if after:
        assert all(row in read_csv(out / "results.csv") for row in kept[1:])


def test_full_disk_while_drawing_leaves_no_half_figure(tmp_path, cli, monkeypatch):
    """A full disk while a figure is saved: one line naming the figure, no temporary file, no report
    linking it; the rerun draws everything."""
    import matplotlib.figure

    def savefig(self, fh, **kw):
        fh.write(b"%PDF half")
        raise OSError(errno.ENOSPC, "No space left on device")

    study = write_study(tmp_path / "study.toml", **small(outputs=["convergence"]))
    out = tmp_path / "out"
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    one_error(cli("study", study, "--out", out), "convergence-occluded-quad-r0.png: cannot write: No space left")
    monkeypatch.undo()
    assert not leftovers(out) and not (out / "report.md").exists()
    assert not list((out / "figures").iterdir())
    assert cli("study", study, "--out", out).status == 0
    assert broken_links(out) == [] and len(list((out / "figures").iterdir())) == 4


def test_a_file_is_replaced_whole_or_not_at_all(tmp_path):
    """warpis.files.replacing, behind every output and cache file: a failure in the writer
    or in the rename leaves the old file and no temporary one; success replaces it with an
    ordinary shareable file."""
    from warpis import files

    target = tmp_path / "kept.json"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="stop"):
        with files.replacing(target, durable=False) as fh:
            fh.write(b"half")
            raise RuntimeError("stop")
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(OSError):  # the rename fails: a folder stands where the file would go
        with files.replacing(folder) as fh:
            fh.write(b"x")
    assert target.read_bytes() == b"old" and not any(folder.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder", "kept.json"]
    with files.replacing(target) as fh:
        fh.write(b"new")
    assert target.read_bytes() == b"new" and target.stat().st_mode & 0o044 == 0o044 & ~files._UMASK


def test_verify_out_full_disk(tmp_path, cli, monkeypatch):
    """verify --out on a full disk: one line, and a verify.json already there stays as it was."""
    out = tmp_path / "out"
    assert cli(*VERIFY, "--out", out).status == 0
    before = (out / "verify.json").read_bytes()
    full_disk(monkeypatch, 0)
    one_error(cli(*VERIFY, "--out", out), f"{out / 'verify.json'}: cannot write: No space left on device")
    monkeypatch.undo()
    assert (out / "verify.json").read_bytes() == before and not leftovers(out)
    full_disk(monkeypatch, 0)
    one_error(cli(*VERIFY, "--out", tmp_path / "new"), "cannot write: No space left on device")
    assert not (tmp_path / "new").exists()


# --------------------------------------------------------------------------- damaged results.csv


def _field(lines: list[str], row: int, column: str, value: str) -> list[str]:
    fields = lines[row].split(",")
    fields[HEADER.index(column)] = value
    return lines[:row] + [",".join(fields)] + lines[row + 1:]


# name → (damage to the lines of results.csv, rows (1-based) it damages, words of the note)
DAMAGE = {
    "non-numeric field": (lambda ls: _field(ls, 1, "variance", "abc"), {1}, "1 unreadable row(s) will be recomputed"),
    "empty field": (lambda ls: _field(ls, 2, "mean", ""), {2}, "1 unreadable row(s)"),
    "bad cell key": (lambda ls: _field(ls, 3, "cell", "zz"), {3}, "1 unreadable row(s)"),
    "truncated last row": (lambda ls: ls[:4] + [ls[4][: len(ls[4]) // 2]], {4}, "1 unreadable row(s)"),
    "wrong column count": (lambda ls: [ls[0], ls[1] + ",9", ls[2], ls[3] + ",x,y", ls[4]], {1, 3},
                           "2 unreadable row(s) will be recomputed"),
    "garbage header": (lambda ls: ["#!garbage\x01,x"] + ls[1:], set(), "header is not warpis's"),
    "a field over the csv size limit": (lambda ls: _field(ls, 4, "scene", "q" * 200_000), {4},
                                        "1 unreadable row(s)"),
    "edited count in a row": (lambda ls: _field(ls, 1, "n", "5"), {1}, "recomputing 1 cell(s)"),
}


@pytest.mark.parametrize("case", list(DAMAGE))
def test_damaged_results_cost_only_their_cells(tmp_path, cli, finished, case):
    """A damaged results.csv: a one-line note, the cells of unreadable rows recomputed, every other row
    kept verbatim (seconds included), the end result equal to the undamaged run's."""
    damage, rows, note = DAMAGE[case]
    study, out = copy_of(finished, tmp_path)
    lines = (out / "results.csv").read_text().splitlines()
    (out / "results.csv").write_text("\n".join(damage(lines)) + "\n")
    result = cli("study", study, "--out", out)
    assert result.status == 0 and result.err == "", result.err
    assert note in result.out
    pristine = read_csv(finished[1] / "results.csv")
    now = read_csv(out / "results.csv")
    assert now[0] == HEADER and without_seconds(now) == without_seconds(pristine)
    cell = {r[-1] for i, r in enumerate(pristine) if i in rows}
    assert [r for r in now[1:] if r[-1] not in cell] == [r for r in pristine[1:] if r[-1] not in cell]
    assert f"computed {len(cell)} cell(s)" in result.out


def test_undecodable_bytes_cost_only_their_row(tmp_path, cli, finished):
    """Bytes that are not UTF-8 inside one row make that row unreadable, not the file."""
    study, out = copy_of(finished, tmp_path)
    data = (out / "results.csv").read_bytes().split(b"\n")
    data[2] = data[2].replace(b"occluded-quad", b"occluded-\xff\xfe", 1)
    (out / "results.csv").write_bytes(b"\n".join(data))
    result = cli("study", study, "--out", out)
    assert result.status == 0 and "1 unreadable row(s)" in result.out and "computed 1 cell(s)" in result.out
    assert without_seconds(read_csv(out / "results.csv")) == without_seconds(read_csv(finished[1] / "results.csv"))


# --------------------------------------------------------------------------- figures and report


def broken_links(out: Path) -> list[str]:
    """Links of report.md (figures and their PDFs) to files that do not exist."""
    report = (out / "report.md").read_text()
    links = re.findall(r"\]\((figures/[^)]+)\)", report)
    return [link for link in links if not (out / link).is_file()]


def test_a_run_stopped_while_drawing_leaves_a_report_whose_links_resolve(tmp_path, cli, monkeypatch):
    """Interrupted after its first new figure, a run leaves the earlier report and every figure it
    links; the next run links only the new figures and removes the stale ones."""
    study = write_study(tmp_path / "study.toml", **small(outputs=["convergence"]))
    out = tmp_path / "out"
    assert cli("study", study, "--out", out).status == 0
    assert broken_links(out) == [] and "convergence-occluded-quad-r1" in (out / "report.md").read_text()
    write_study(study, **small(outputs=["convergence"], receivers=[2, 5]))
    real, calls = plots._save, []

    def save(fig, where, stem):
        calls.append(stem)
        if len(calls) > 1:
            raise KeyboardInterrupt
        return real(fig, where, stem)

    monkeypatch.setattr(plots, "_save", save)
    assert cli("study", study, "--out", out).status == 130
    monkeypatch.undo()
    assert broken_links(out) == [] and "-r1" in (out / "report.md").read_text() and not leftovers(out)
    assert cli("study", study, "--out", out).status == 0
    report = (out / "report.md").read_text()
    assert broken_links(out) == [] and "-r5.png" in report and "-r1" not in report
    assert sorted(p.name for p in (out / "figures").iterdir()) == [
        f"convergence-occluded-quad-r{r}.{e}" for r in (2, 5) for e in ("pdf", "png")]


def drawing_process() -> tuple[int, bool]:
    """A stand-in figure job for draw_all: the process that ran it, and whether it ignores Ctrl-C."""
    return os.getpid(), signal.getsignal(signal.SIGINT) == signal.SIG_IGN


def crash_outside(parent: int) -> int:
    """A stand-in figure job that kills any process but ``parent`` (as a crash of the helper would)."""
    if os.getpid() != parent:
        os._exit(3)
    return parent


def test_a_second_process_draws_from_the_front_while_this_one_draws_from_the_back():
    """With two cores and HELPER_FROM figures a spawned helper takes the first job (this process
    draws the rest while it starts); fewer figures, or one core, are drawn here in order.  The
    helper ignores Ctrl-C (this process alone answers it, in one line); this one keeps its handler."""
    jobs = [functools.partial(drawing_process) for _ in range(plots.HELPER_FROM)]
    handler = signal.getsignal(signal.SIGINT)
    here = (os.getpid(), handler == signal.SIG_IGN)
    made = plots.draw_all(jobs, processes=2)
    assert isinstance(made[0], tuple) and made[0][0] != here[0] and made[0][1]
    assert made[1:] == [here] * (plots.HELPER_FROM - 1) and signal.getsignal(signal.SIGINT) is handler
    assert plots.draw_all(jobs, processes=1) == [here] * plots.HELPER_FROM
    assert plots.draw_all(jobs[1:], processes=2) == [here] * (plots.HELPER_FROM - 1)


def test_a_helper_that_dies_costs_only_time():
    """A helper that dies leaves its job to this process, which draws every figure (a figure
    the helper cannot write is one line: test_a_figure_the_helper_cannot_write_...)."""
    here = os.getpid()
    assert plots.draw_all([functools.partial(crash_outside, here)] * plots.HELPER_FROM, processes=2) == \
        [here] * plots.HELPER_FROM


def test_a_study_drawn_in_two_processes_writes_the_same_files(tmp_path, cli, monkeypatch):
    """The helper from two figures on: ``--threads 2`` writes the figures (PNG bytes) that
    ``--threads 1`` writes, and its report links them alike."""
    monkeypatch.setattr(plots, "HELPER_FROM", 2)
    study = write_study(tmp_path / "study.toml", **small(outputs=["convergence"]))
    runs = {}
    for threads in ("1", "2"):
        out = tmp_path / f"out{threads}"
        assert cli("study", study, "--out", out, "--threads", threads).status == 0
        runs[threads] = {p.name: p.read_bytes() for p in sorted((out / "figures").glob("*.png"))}
        runs[threads]["links"] = re.findall(r"\]\((figures/[^)]+)\)", (out / "report.md").read_text())
    assert len(runs["1"]) == 3 and len(runs["1"]["links"]) == 4 and runs["1"] == runs["2"]


def test_a_figure_the_helper_cannot_write_is_one_line_and_no_report(tmp_path, cli, monkeypatch):
    """Two convergence figures on two threads, the helper from two figures on: the helper draws
    the first, whose path is a folder; one line names it, and no temporary file or report is left."""
    monkeypatch.setattr(plots, "HELPER_FROM", 2)
    study = write_study(tmp_path / "study.toml", **small(outputs=["convergence"]))
    out = tmp_path / "out"
    (out / "figures" / "convergence-occluded-quad-r0.png").mkdir(parents=True)
    one_error(cli("study", study, "--out", out, "--threads", "2"), "convergence-occluded-quad-r0.png: cannot write")
    assert not leftovers(out) and not (out / "report.md").exists()
    assert (out / "figures" / "convergence-occluded-quad-r1.png").is_file()  # drawn here, beside the helper


@pytest.mark.parametrize("names", [("a/b", "a:b"), ("a b", "a?b")])
def test_scene_names_that_are_not_file_names_get_distinct_figures(tmp_path, cli, names):
    """Two scenes whose names differ only in characters a file name cannot hold draw distinct
    figures, both linked from the report."""
    for i, name in enumerate(names):
        write_scene(tmp_path / f"s{i}", name=name)
    study = write_study(tmp_path / "study.toml", **small(scenes=["s0/scene.toml", "s1/scene.toml"], receivers=[0],
                                                         estimators=ESTIMATORS[:1], outputs=["convergence"]))
    out = tmp_path / "out"
    result = cli("study", study, "--out", out)
    assert result.status == 0, result.err
    assert len(list((out / "figures").glob("convergence-*.png"))) == 2 and broken_links(out) == []


SLUGS = {
    "occluded-quad": "occluded-quad",  # a file name already: unchanged (figure names stay as they were)
    "grid_floor.v2": "grid_floor.v2",
    "a/b": re.compile(r"a-b-[0-9a-f]{8}"),
    "": re.compile(r"[0-9a-f]{8}"),
    "x" * 300: re.compile(r"x{64}-[0-9a-f]{8}"),
}


def test_slugs_are_file_names_and_distinct():
    """Scene names → figure name parts: file-name characters only, at most 73 of them, and distinct
    for distinct names."""
    for name, want in SLUGS.items():
        got = plots._slug(name)
        assert got == want if isinstance(want, str) else want.fullmatch(got), (name, got)
    names = ["a/b", "a:b", "a b", "a?b", "a\\b", "a-b", "a*b", "a\nb"]
    assert len({plots._slug(n) for n in names}) == len(names)


# --------------------------------------------------------------------------- counts and study files

BIG = 99999999999999999999999
BAD_COUNTS = {
    "trials beyond 64 bits": (small(trials=BIG), "trials: must be at most 2,147,483,647"),
    "trials beyond int32": (small(trials=2**31), "trials: must be at most"),
    "trials the memory cannot hold": (small(trials=2**31 - 1, receivers=list(range(8))), "trials: would need"),
    "an N beyond 32 bits": (small(n=[4, 4294967300]), "n: must be at most"),
    "N zero": (small(n=[0]), "n: must be at least 1"),
    "N not an integer": (small(n=[4.5]), "n: expected an integer"),
    "a receiver beyond 64 bits": (small(receivers=[99999999999999999999]),
                                  "receivers: receiver 99999999999999999999 does not exist"),
    "a receiver in a table": (small(receivers={"occluded-quad": [-1]}),
                              "receivers of 'occluded-quad': receiver -1 does not exist"),
    "a repeated receiver": (small(receivers=[1, 1]), "receivers lists 1 twice"),
    "a seed beyond 32 bits": (small(seed=2**32), "seed: must be in [0, 2^32)"),
    "a negative seed": (small(seed=-1), "seed: must be in [0, 2^32)"),
    "threads beyond int32": (small(threads=BIG), "threads: must be at most"),
    "threads zero": (small(threads=0), "threads: must be at least 1"),
}


@pytest.mark.parametrize("case", list(BAD_COUNTS))
def test_counts_the_kernels_cannot_hold_fail_before_any_file(tmp_path, cli, case):
    """A count, seed or receiver the kernels cannot hold: one line naming the study file and the key,
    status 2, and no output folder at all."""
    keys, words = BAD_COUNTS[case]
    study = write_study(tmp_path / "study.toml", **keys)
    out = tmp_path / "out"
    line = one_error(cli("study", study, "--out", out), words)
    assert line.startswith(f"warpis: error: {study}: ")
    assert not out.exists()


UNREADABLE_STUDY = {
    "nested 50,000 deep": ("[study]\nx = " + "[" * 50_000 + "]" * 50_000 + "\n", "not valid TOML"),
    "not UTF-8": (b"[study]\nname = \"\xff\"\n", "not UTF-8"),
    "not TOML": ("[study\n", "not valid TOML"),
}


@pytest.mark.parametrize("case", list(UNREADABLE_STUDY))
def test_unreadable_study_files_are_one_line(tmp_path, cli, case):
    content, words = UNREADABLE_STUDY[case]
    study = tmp_path / "study.toml"
    study.write_bytes(content if isinstance(content, bytes) else content.encode())
    line = one_error(cli("study", study, "--out", tmp_path / "out"), words)
    assert line.startswith(f"warpis: error: {study}: ") and not (tmp_path / "out").exists()
