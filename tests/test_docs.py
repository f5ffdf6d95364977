"""README.md and docs/*.md against the code they describe.

* Every ``warpis ...`` command of their fenced code blocks (a line starting with
  ``warpis `` or ``$ warpis ``; a trailing backslash continues it, ``#`` starts a comment,
  and a line whose comment says ``synopsis`` shows a command's shape and is skipped:
  ``scripts/readme_verify.py``'s ``doc_commands``) parses with warpis's own argument
  parser (abbreviated flags refused), so a stale or misspelled command or flag fails here,
  naming the page and line.
* Every relative link (and image) points at a file that exists, and a ``#anchor`` into a
  Markdown page at one of its headings.
* The README stays short: at most 250 lines.
* The cheapest documented commands run for real, in process, in seconds; the bad-input
  page's example prints the error the page shows.

``python scripts/readme_verify.py --run`` runs every documented command for real (slow,
not part of the suite).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import sys
from pathlib import Path

import pytest

from warpis.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from readme_verify import DocCommand, doc_commands, doc_pages  # noqa: E402

README_MAX_LINES = 250
# Commands that run in seconds, each of which the documentation must keep showing.
CHEAP = (
    ("docs/scene-files.md", ["scenes"]),
    ("docs/scene-files.md", ["info", "meshes/occluded-quad/scene.toml"]),
    ("docs/estimators.md", ["estimate", "--help"]),
)
COMMANDS = doc_commands()


def _strict_parser() -> argparse.ArgumentParser:
    """warpis's parser, taking no abbreviated flag: the documentation spells each in full."""
    parser = build_parser()
    todo = [parser]
    while todo:
        p = todo.pop()
        p.allow_abbrev = False
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                todo.extend(action.choices.values())
    return parser


def _parse_error(argv: list[str]) -> str | None:
    """None when warpis's parser takes ``argv``, else its error line."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            _strict_parser().parse_args(argv)
    except SystemExit as exc:
        if exc.code not in (0, None):  # 0: --help / --version
            return err.getvalue().strip() or f"exit status {exc.code}"
    return None


def test_the_documentation_shows_commands():
    pages = {c.page for c in COMMANDS}
    assert "README.md" in pages and len(COMMANDS) >= 10, pages


def _failure(cmd: DocCommand) -> str | None:
    """None when ``cmd`` parses, else a message naming its page and line."""
    error = _parse_error(cmd.argv)
    return None if error is None else f"{cmd.page}:{cmd.line}: `{cmd.text}` does not parse: {error}"


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: f"{c.page}:{c.line}")
def test_every_documented_command_parses(cmd: DocCommand):
    failure = _failure(cmd)
    assert failure is None, failure


def test_a_misspelled_flag_fails_with_page_and_line(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("text\n\n```bash\n# a comment\nwarpis info SCENE [--json]   # synopsis\n"
                    "$ warpis estimate occluded-quad --estimator independent:single:light-area \\\n"
                    "    --n 16 --trails 100   # a typo\n```\n\nwarpis info x --jsn\n")
    commands = doc_commands([page])
    assert [(c.line, c.argv[-2:]) for c in commands] == [(6, ["--trails", "100"])]
    failure = _failure(commands[0])
    assert failure is not None and f"{page}:6:" in failure and "--trails" in failure, failure


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _prose(text: str) -> str:
    """``text`` without its fenced blocks and inline code spans."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of the headings of ``page``."""
    out = set()
    for line in _prose(page.read_text()).splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            out.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return out


def _links() -> list[tuple[str, int, str]]:
    found = []
    for page in doc_pages():
        text = page.read_text()
        prose = _prose(text)
        # line numbers from the original text: search each link's own text there
        for match in LINK.finditer(prose):
            target = match.group(1)
            line = text[: text.find(match.group(0))].count("\n") + 1 if match.group(0) in text else 0
            found.append((str(page.relative_to(ROOT)), line, target))
    return found


def test_every_relative_link_points_at_an_existing_file():
    bad = []
    links = _links()
    assert len(links) >= 20
    for page, line, target in links:
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:, ...
            continue
        path, _, anchor = target.partition("#")
        file = (ROOT / page).parent / path if path else ROOT / page
        if not file.exists():
            bad.append(f"{page}:{line}: {target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            bad.append(f"{page}:{line}: {target}: no heading #{anchor} in {file.relative_to(ROOT)}")
    assert not bad, "\n".join(bad)


def test_every_docs_page_is_listed_in_the_readme():
    readme = (ROOT / "README.md").read_text()
    missing = [p.name for p in sorted((ROOT / "docs").glob("*.md")) if f"(docs/{p.name})" not in readme]
    assert not missing, f"README.md's Documentation list lacks {missing}"


def test_the_readme_fits_on_a_few_screens():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines (at most {README_MAX_LINES})"


def test_the_readme_shows_the_ci_test_command():
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    readme = (ROOT / "README.md").read_text()
    assert f"```bash\n{ci}\n```" in readme, ci


@pytest.mark.parametrize("page, argv", CHEAP, ids=lambda x: " ".join(x) if isinstance(x, list) else x)
def test_the_cheap_documented_commands_run(page, argv, monkeypatch, capsys):
    assert any(c.page == page and c.argv == argv for c in COMMANDS), f"{page} no longer shows `warpis {' '.join(argv)}`"
    monkeypatch.chdir(ROOT)
    try:
        status = main(argv)
    except SystemExit as exc:  # --help
        status = exc.code or 0
    out = capsys.readouterr()
    assert status == 0, out.err
    assert out.out.strip(), f"`warpis {' '.join(argv)}` printed nothing"


def test_the_bad_input_example_prints_what_the_page_shows(capsys):
    page = ROOT / "docs" / "bad-input.md"
    cmd = next(c for c in COMMANDS if c.page == "docs/bad-input.md")
    shown = re.search(r"^```\n(warpis: error: [^\n]*)\n```", page.read_text(), flags=re.M).group(1)
    assert main(cmd.argv) == 2
    assert capsys.readouterr().err.strip() == shown


def test_the_layout_names_every_module():
    """docs/development.md's layout lists every module of the package (a subpackage's
    own modules by its folder), so a new file cannot go unexplained."""
    page = (ROOT / "docs" / "development.md").read_text()
    layout = page[page.index("```\nwarpis/\n"):]
    layout = layout[:layout.index("\n```", 4)]
    named = set(re.findall(r"[\w/]+(?:\.py|/)", layout))
    missing = []
    for path in sorted((ROOT / "warpis").rglob("*.py")):
        parts = path.relative_to(ROOT / "warpis").parts
        if parts[-1] == "__init__.py" and len(parts) > 1:
            continue
        wanted = parts[-1] if len(parts) <= 2 else f"{parts[1]}/"
        if wanted not in named:
            missing.append("/".join(parts))
    assert len(named) > 40, "the layout block was not found"
    assert not missing, f"docs/development.md's layout does not name: {', '.join(missing)}"
