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


# What each room may not import: lower rooms never reach up (issue 30: the sampling rules live in
# data/, the image helpers in eval/, so neither lifts data/ above acquisition nor the viewer into
# the experiment layer).
NOT_ABOVE = {
    "splat": {"fisher", "acquisition", "fit", "data", "active", "eval", "experiment", "report", "view"},
    "fisher": {"acquisition", "fit", "data", "active", "experiment", "report", "view"},
    "data": {"acquisition", "fisher", "fit", "active", "experiment", "report", "view"},
    "eval": {"acquisition", "active", "experiment", "report", "view"},
    "acquisition": {"active", "experiment", "report", "view"},
}  # view/ still reads a job's config through experiment.build (the typed run spine will own it)


def pipeline_rooms(path: Path) -> set[str]:
    rooms = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                 [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
        rooms |= {n.split(".")[1] for n in names if n.startswith("pipeline.") and n.count(".") >= 1}
    return rooms


@pytest.mark.parametrize("part", sorted(NOT_ABOVE))
def test_a_room_does_not_import_the_rooms_above_it(part):
    for path in files(part):
        bad = pipeline_rooms(path) & NOT_ABOVE[part]
        assert not bad, f"{path} imports pipeline.{sorted(bad)}"


def test_no_module_imports_another_modules_private_names():
    for path in files("."):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("pipeline"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert not private, f"{path} imports {private} from {node.module}"


def test_the_fisher_walks_only_the_declared_surface_of_the_compositor():
    from pipeline.splat import rasterize
    tree = ast.parse((ROOT / "fisher" / "exact.py").read_text())
    used = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
            and n.module == "pipeline.splat.rasterize" for a in n.names}
    assert used and used <= set(rasterize.__all__), used - set(rasterize.__all__)


def test_nothing_imports_the_commands():
    """pipeline/cli is the outermost room: the commands import the library, never the reverse."""
    for path in files("."):
        if path.parent.name == "cli":
            continue
        assert "cli" not in pipeline_rooms(path), f"{path} imports pipeline.cli"
