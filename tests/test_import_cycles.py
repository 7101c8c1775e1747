"""No import cycle among the package's modules, counting the imports placed inside functions (they
hide a cycle from import-linter, which checks only between packages) and not those under
``if TYPE_CHECKING:`` (never run). A cycle is named module by module."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"


def module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def type_checking_nodes(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", None)) == "TYPE_CHECKING":
            skip |= {id(n) for branch in node.body for n in ast.walk(branch)}
    return skip


def imported(path: Path, root: Path, modules: set[str]) -> set[str]:
    """The package's modules ``path`` imports anywhere in it (a name imported from a package is
    its submodule when there is one, else the package's ``__init__``)."""
    tree = ast.parse(path.read_text())
    skip = type_checking_nodes(tree)
    here = module_name(path, root)
    package = here if path.name == "__init__.py" else here.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            for alias in node.names:
                target = f"{base}.{alias.name}"
                out.add(target if target in modules else base)
    return {m for m in out if m in modules and m != here}


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    return {name: imported(path, root, set(files)) for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iteratively)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_package_has_no_import_cycle():
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_cycle_finder_sees_a_cycle_hidden_in_a_function_and_ignores_type_checking(tmp_path):
    root = tmp_path / "pipeline"
    (root / "sub").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "sub" / "__init__.py").write_text("from pipeline.sub.a import A\n")
    (root / "sub" / "a.py").write_text("def f():\n    from pipeline.sub import b\n")
    (root / "sub" / "b.py").write_text("from .a import f\n")
    (root / "sub" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                       "    from pipeline.sub.d import D\n")
    (root / "sub" / "d.py").write_text("from pipeline.sub.c import C\n")
    graph = import_graph(root)
    assert graph["pipeline.sub.b"] == {"pipeline.sub.a"} and graph["pipeline.sub.c"] == set()
    assert cycles(graph) == [["pipeline.sub.a", "pipeline.sub.b"]]
    # a package importing its submodule, which takes a re-exported name from the package: a cycle
    graph["pipeline.sub.a"].add("pipeline.sub")
    assert ["pipeline.sub", "pipeline.sub.a", "pipeline.sub.b"] in cycles(graph)


@pytest.mark.parametrize("planted", ["pipeline/experiment/spec.py", "pipeline/data/scene.py"])
def test_the_cycles_that_were_broken_would_be_seen_again(planted):
    graph = import_graph()
    back = {"pipeline/experiment/spec.py": ("pipeline.experiment.spec", "pipeline.experiment.build"),
            "pipeline/data/scene.py": ("pipeline.data.scene", "pipeline.data.readers")}[planted]
    graph[back[0]].add(back[1])  # the function-level import each had
    assert any(set(back) <= set(c) for c in cycles(graph))
