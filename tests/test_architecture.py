"""The floors of the house (docs/architecture.md), read from the imports with ``ast``.

Every import in the package — at module level or inside a function, where a circle
likes to hide — is an arrow from one module to another.  A module may import its own
floor or the floors below it, never one above; no module imports another's private
name (``_x``); the arrows make no circle; and the scenes floor, plain numpy data, never
imports Warp, so a scene source loads and is tested without compiling a kernel.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "warpis"

# Bottom to top.  A module's floor is that of its longest matching prefix.
FLOORS = {
    "warpis.errors": 0, "warpis.files": 0, "warpis.vocabulary": 0, "warpis.limits": 0, "warpis.version": 0, "warpis.stats": 0,
    "warpis.scenes": 1, "warpis.point_sets": 1,
    "warpis.kernels": 2,
    "warpis.analysis": 3,
    "warpis.runs": 4, "warpis.plots": 4,
    "warpis.cli": 5, "warpis.testing": 5, "warpis.check": 5, "warpis": 5,
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def floor(module: str) -> int:
    while module not in FLOORS:
        module = module.rpartition(".")[0]
    return FLOORS[module]


def imports(path: Path) -> list[tuple[str, str, int]]:
    """(imported module, imported name or '', line) for every import in ``path``."""
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, "", node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package
            for _ in range(node.level - 1):
                base = base.rpartition(".")[0]
            source = node.module if node.level == 0 else ".".join(p for p in (base, node.module) if p)
            for a in node.names:
                sub = f"{source}.{a.name}"  # `from . import x` imports the module x
                is_module = (PACKAGE.parent / sub.replace(".", "/")).with_suffix(".py").exists() or \
                    (PACKAGE.parent / sub.replace(".", "/") / "__init__.py").exists()
                out.append((sub, "", node.lineno) if is_module else (source, a.name, node.lineno))
    return out


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
EDGES = {m: [(t, name, line) for t, name, line in imports(p) if t.split(".")[0] == "warpis"]
         for m, p in MODULES.items()}


def test_the_walk_sees_the_package():
    """The reader finds the floors' modules and the arrows between them (a reader that
    saw nothing would pass every test below)."""
    assert {"warpis.scenes.description", "warpis.kernels.device", "warpis.cli"} <= set(MODULES)
    targets = {t for t, _, _ in EDGES["warpis.kernels.engine"]}
    assert "warpis.kernels.device" in targets and "warpis.errors" in targets


def test_no_import_points_up():
    up = [f"{m}:{line} imports {t} (floor {floor(t)} above {floor(m)})"
          for m, edges in EDGES.items() for t, _, line in edges
          if m != "warpis" and floor(t) > floor(m)]
    assert not up, "\n".join(up)


def test_no_private_name_crosses_a_module():
    private = [f"{m}:{line} imports {t}.{name}" for m, edges in EDGES.items() for t, name, line in edges
               if name.startswith("_") and not name.startswith("__") and t != m]
    private += [f"{m}:{line} imports module {t}" for m, edges in EDGES.items() for t, _, line in edges
                if t.rpartition(".")[2].startswith("_") and not t.endswith("__init__")]
    assert not private, "\n".join(private)


def test_no_circle():
    """Depth-first search over module arrows (a package's __init__ re-exporting its
    modules is an arrow like any other)."""
    graph = {m: sorted({_known(t) for t, _, _ in edges} - {m, None}) for m, edges in EDGES.items()}
    state: dict[str, int] = {}
    circles: list[list[str]] = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for t in graph.get(m, ()):
            if state.get(t) == 1:
                circles.append(path[path.index(t):] + [t])
            elif t not in state:
                visit(t, path + [t])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [m])
    # A package's __init__ importing its own modules, and they importing a sibling
    # through the package, is how Python packages work; any other loop is a circle.
    assert not circles, "\n".join(" → ".join(c) for c in circles)


def _known(target: str) -> str | None:
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target or None


def module_level_warp(path: Path) -> list[int]:
    """Lines where ``path`` imports Warp outside any function (an import inside a function
    runs only when that function is called: a user's Warp function checked, a CUDA name)."""
    lines = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(child, ast.Import) and any(a.name.split(".")[0] == "warp" for a in child.names):
                lines.append(child.lineno)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and \
                    (child.module or "").split(".")[0] == "warp":
                lines.append(child.lineno)
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    return lines


def test_the_warp_reader_sees_an_import():
    assert module_level_warp(MODULES["warpis.kernels.device"]), "kernels/device.py imports Warp at module level"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if floor(m) <= 1))
def test_the_floors_under_the_kernels_import_no_warp_on_load(module):
    lines = module_level_warp(MODULES[module])
    assert not lines, f"{module} imports warp at line(s) {lines}"


def test_a_wheel_ships_every_package_scene_and_compiled_kernel():
    """The suite runs on an editable install, which finds every folder; a user's
    ``pip install .`` ships only what pyproject.toml lists: every package of warpis, every
    file of the bundled scenes, and the kernels compiled ahead of time."""
    import fnmatch
    import tomllib

    root = PACKAGE.parent
    conf = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert {module_name(p) for p in PACKAGE.rglob("__init__.py")} <= set(conf["packages"])
    for package, folder in (("warpis.meshes", "meshes"), ("warpis.kernels.precompiled", "warpis/kernels/precompiled")):
        files = [p.relative_to(root / folder).as_posix() for p in (root / folder).rglob("*")
                 if p.is_file() and p.suffix not in (".py", ".pyc")]
        globs = conf["package-data"][package]
        assert files and not [f for f in files if not any(fnmatch.fnmatch(f, g) for g in globs)], package
