"""The package layout of issue 43 stays as designed: modules of at most ~400 lines, no import circle, no
private helper at the package root but the version (docs/architecture.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"mssf_blocks": ROOT / "src" / "mssf_blocks", "mssf_examples": ROOT / "examples" / "mssf_examples"}
MAX_LINES = 400


def _modules(package: str):
    base = PACKAGES[package]
    for f in sorted(base.rglob("*.py")):
        rel = f.relative_to(base.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), f


def _module_level_imports(name: str, path: Path, known: set) -> set:
    """Modules of the package that ``name`` imports when it is imported (not inside functions)."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    out = set()

    def add(target: str) -> None:
        # the longest known module prefix (``from a.b import c`` imports a.b, and a.b.c when c is a module)
        parts = target.split(".")
        for k in range(len(parts), 0, -1):
            cand = ".".join(parts[:k])
            if cand in known:
                out.add(cand)
                return

    def visit(nodes) -> None:
        for node in nodes:
            if isinstance(node, ast.Import):
                for a in node.names:
                    add(a.name)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                subs = [f"{mod}.{a.name}" for a in node.names]
                for sub in subs:
                    add(sub)
                if not all(sub in known for sub in subs):  # (``from pkg import module`` runs only the module)
                    add(mod)
            elif isinstance(node, ast.If):
                test = ast.unparse(node.test)
                if "TYPE_CHECKING" not in test:
                    visit(node.body)
                    visit(node.orelse)
            elif isinstance(node, ast.Try):
                visit(node.body)
                for h in node.handlers:
                    visit(h.body)
                visit(node.orelse)
                visit(node.finalbody)

    visit(tree.body)
    out.discard(name)
    return out


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_no_module_is_longer_than_the_limit(package):
    long = {name: n for name, f in _modules(package) if (n := len(f.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them by concept): {long}"


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_no_import_circle(package):
    mods = dict(_modules(package))
    known = set(mods)
    graph = {name: _module_level_imports(name, f, known) for name, f in mods.items()}
    # a package's __init__ importing its own submodules is how a package exports; a circle through
    # a parent package's __init__ counts only when the submodule imports the package back
    state, stack, circles = {}, [], []

    def dfs(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                circle = stack[stack.index(nxt):] + [nxt]
                if not all(b.startswith(a + ".") for a, b in zip(circle, circle[1:])):
                    circles.append(" -> ".join(circle))
            elif nxt not in state:
                dfs(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            dfs(node)
    assert not circles, "import circles:\n" + "\n".join(circles)


def test_the_library_root_holds_no_private_helper_but_the_version():
    root = PACKAGES["mssf_blocks"]
    private = sorted(f.name for f in root.glob("_*.py") if f.name not in ("__init__.py", "_version.py"))
    assert not private, f"private modules at the package root (move them into the subpackage that uses them): {private}"
    assert not (root / "compat").exists(), "'compat' says nothing: name what a module is compatible with"


def test_a_circle_is_found():
    """The detector itself: a two-module circle in a throwaway package is reported."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        pkg = Path(d) / "pkg"
        pkg.mkdir()
        (pkg / "__init__.py").write_text("")
        (pkg / "a.py").write_text("from pkg.b import x\n")
        (pkg / "b.py").write_text("from pkg import a\nfrom pkg import y\nx = 1\n")
        (pkg / "c.py").write_text("def f():\n    from pkg import a\n")  # inside a function: not at import
        known = {"pkg", "pkg.a", "pkg.b", "pkg.c"}
        assert _module_level_imports("pkg.a", pkg / "a.py", known) == {"pkg.b"}
        assert _module_level_imports("pkg.b", pkg / "b.py", known) == {"pkg.a", "pkg"}
        assert _module_level_imports("pkg.c", pkg / "c.py", known) == set()
