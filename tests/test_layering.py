"""Dependencies point one way: the core never imports the orchestration or plotting stack, and
reports never import torch (checked on the source, so it fails as soon as someone adds one)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "pipeline"
EDGE_ONLY = {"hydra", "omegaconf", "ray", "mlflow", "matplotlib", "viser", "playwright"}
CORE = ["splat", "fisher", "acquisition", "fit", "data", "active", "eval", "cameras.py", "memory.py"]


def imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split(".")[0])
    return roots


def files(part: str) -> list[Path]:
    target = ROOT / part
    return [target] if target.is_file() else sorted(target.rglob("*.py"))


@pytest.mark.parametrize("part", CORE)
def test_core_does_not_import_orchestration_or_plotting(part):
    for path in files(part):
        assert not imported_roots(path) & EDGE_ONLY, f"{path} imports {imported_roots(path) & EDGE_ONLY}"


def test_reports_do_not_import_torch():
    for path in files("report"):
        assert "torch" not in imported_roots(path), path
