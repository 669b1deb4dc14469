"""The package as a whole: one version string, licence and citation files, no import cycles."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import posernet

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "posernet"


def test_one_version_string() -> None:
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^dynamic = \["version"\]', pyproject, re.M)
    assert 'version = {attr = "posernet.__version__"}' in pyproject
    assert not re.search(r'^version = "', pyproject, re.M)  # not written a second time
    cff = (ROOT / "CITATION.cff").read_text()
    assert re.search(rf"^version: {re.escape(posernet.__version__)}$", cff, re.M)
    assert "PoserNet: Refining Relative Camera Poses Exploiting Object Detections" in cff
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_package(name: str) -> bool:
    return (SRC.parent / name.replace(".", "/") / "__init__.py").is_file()


def _exists(name: str) -> bool:
    p = SRC.parent / name.replace(".", "/")
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _imports(path: Path) -> set[str]:
    """posernet modules that ``path`` imports, at module level or inside functions (a deferred
    import still ties the two modules together); not those under ``if TYPE_CHECKING``."""
    name = _module_name(path)
    package = name if _is_package(name) else name.rsplit(".", 1)[0]
    out: set[str] = set()

    class Visitor(ast.NodeVisitor):
        def visit_If(self, node: ast.If) -> None:
            if "TYPE_CHECKING" in ast.unparse(node.test):
                for child in node.orelse:
                    self.visit(child)
            else:
                self.generic_visit(node)

        def visit_Import(self, node: ast.Import) -> None:
            out.update(a.name for a in node.names if a.name.startswith("posernet"))

        def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("posernet"):
                for a in node.names:
                    sub = f"{mod}.{a.name}"
                    out.add(sub if _exists(sub) else mod)

    Visitor().visit(ast.parse(path.read_text()))
    out.discard(name)
    return out


def test_no_import_cycle_inside_posernet() -> None:
    graph = {_module_name(p): _imports(p) for p in SRC.rglob("*.py")}
    # a package importing its own submodules is how packages work, not a cycle: drop the
    # edge from a module to a package that contains it
    for mod, deps in graph.items():
        graph[mod] = {d for d in deps if not mod.startswith(d + ".")}
    cycles = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def walk(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                cycles.append(" -> ".join([*stack[stack.index(d):], d]))
            elif d not in state:
                walk(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            walk(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_cycle_check_sees_a_cycle(tmp_path, monkeypatch) -> None:
    """The check itself: two modules importing each other at module level are found."""
    pkg = tmp_path / "posernet"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from .b import x\n")
    (pkg / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                              "    from .c import y\nfrom . import a\n")
    (pkg / "c.py").write_text("")
    monkeypatch.setattr(__import__(__name__), "SRC", pkg)
    assert _imports(pkg / "a.py") == {"posernet.b"}  # a deferred import counts
    assert _imports(pkg / "b.py") == {"posernet.a"}  # TYPE_CHECKING left out


def test_no_private_name_is_imported_from_another_module() -> None:
    """A name one module shares with another is public (no ``from .x import _helper``)."""
    found = []
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                found += [f"{_module_name(path)}: from {'.' * node.level}{node.module or ''} "
                          f"import {a.name}" for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]
    assert not found, "\n".join(found)


def test_hydra_instantiate_only_in_the_command_layer() -> None:
    """The library takes built objects; configs become objects in ``posernet.cli`` only."""
    found = []
    for path in SRC.rglob("*.py"):
        if (SRC / "cli") in path.parents:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("hydra") \
                    and any(a.name == "instantiate" for a in node.names):
                found.append(_module_name(path))
    assert not found, found


def test_no_two_modules_share_a_base_name() -> None:
    """``refine.py`` in three packages meant three different things; every module name is
    now unique in the package (``__init__`` / ``__main__`` aside), so a name says which."""
    seen: dict[str, list[str]] = {}
    for path in sorted(SRC.rglob("*.py")):
        if path.stem not in ("__init__", "__main__"):
            seen.setdefault(path.stem, []).append(_module_name(path))
    shared = {k: v for k, v in seen.items() if len(v) > 1}
    assert not shared, f"modules sharing a base name: {shared}"
