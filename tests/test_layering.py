"""Dependencies point one way: import-linter's contracts (pyproject.toml) for the rooms' layers
and the edge-only libraries, plus what it cannot express: no private imports across modules, the
Fisher walk's declared surface of the compositor."""

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "pipeline"
ROOT_DIR = ROOT.parent


def files(part: str) -> list[Path]:
    target = ROOT / part
    return [target] if target.is_file() else sorted(target.rglob("*.py"))


def lint(project: Path) -> subprocess.CompletedProcess:
    """import-linter over ``project``'s pipeline package with ``project``'s pyproject contracts."""
    env = {**os.environ, "PYTHONPATH": str(project)}
    return subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports; "
                           "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True, no_logo=True))"],
                          cwd=project, env=env, capture_output=True, text=True)


def test_the_import_contracts_hold():
    """pyproject.toml's [tool.importlinter] contracts: the rooms' layers, the edge-only libraries
    (hydra, omegaconf, ray, mlflow, matplotlib, viser, playwright never in the core), reports
    without torch."""
    done = lint(ROOT_DIR)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "6 kept, 0 broken" in done.stdout


@pytest.mark.parametrize("room,line,broken", [
    ("splat/render.py", "import pipeline.fisher.exact", "rooms point one way"),
    ("fisher/posterior.py", "import mlflow", "the core never imports"),
    ("report/tables.py", "import torch", "reports read records"),
])
def test_the_import_contracts_catch_a_planted_import(tmp_path, room, line, broken):
    shutil.copytree(ROOT, tmp_path / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT_DIR / "pyproject.toml", tmp_path)
    target = tmp_path / "pipeline" / room
    target.write_text(target.read_text() + f"\n{line}  # planted\n")
    done = lint(tmp_path)
    assert done.returncode != 0 and "1 broken" in done.stdout, done.stdout
    assert broken in done.stdout.split("Broken contracts")[1]


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
