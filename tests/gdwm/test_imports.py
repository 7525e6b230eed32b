"""No import loops inside the platform: every ``import`` of ``gdwm`` modules, lazy ones inside functions included,
forms a DAG (a loop is a module that can't be understood, or imported first, without the other)."""

from __future__ import annotations

import ast
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

PLATFORM = Path(__file__).resolve().parents[2] / "platform"


def module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    return ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)


def imported(path: Path, name: str, known: set[str]) -> set[str]:
    """The ``known`` modules ``path`` imports anywhere in its body (``from a import b`` counts ``a`` and ``a.b``)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, *([base] if base else [])])
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return {m for m in out if m in known and m != name}


def import_graph(root: Path) -> dict[str, set[str]]:
    paths = {module_name(p, root): p for p in (root / "gdwm").rglob("*.py")}
    return {name: imported(p, name, set(paths)) for name, p in paths.items()}


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    try:
        TopologicalSorter(graph).prepare()
    except CycleError as e:
        return list(e.args[1])
    return None


def test_the_platform_has_no_import_cycle():
    graph = import_graph(PLATFORM)
    assert len(graph) > 30 and "gdwm.config" in graph["gdwm.regress"]  # the walk sees the package and its edges
    assert cycle(graph) is None, f"import cycle: {' -> '.join(cycle(graph))}"


def test_the_walk_finds_a_cycle_through_a_lazy_import(tmp_path):
    pkg = tmp_path / "gdwm"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from gdwm.b import g\n")
    (pkg / "b.py").write_text("from . import a\n")
    (pkg / "c.py").write_text("import gdwm.a\n")
    graph = import_graph(tmp_path)
    assert graph == {"gdwm": set(), "gdwm.a": {"gdwm.b"}, "gdwm.b": {"gdwm", "gdwm.a"}, "gdwm.c": {"gdwm.a"}}
    assert sorted(set(cycle(graph))) == ["gdwm.a", "gdwm.b"]
