"""Which code produced a run, recorded on every job (records column and MLflow tag).

``code_version()``: the git commit of the checkout the package runs from, with ``-dirty`` when
tracked files have uncommitted changes; outside a git checkout, ``gopre <installed version>``.
A sweep relaunched after the code changed keeps its finished jobs (they are identified by what
they compute, not by the code) and says so, naming both versions.
"""

from __future__ import annotations

import subprocess
from functools import lru_cache
from importlib import metadata
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@lru_cache(maxsize=None)
def code_version(root: Path = PACKAGE_ROOT) -> str:
    commit = _git(root, "rev-parse", "--short=12", "HEAD")
    if commit:
        dirty = _git(root, "status", "--porcelain", "--untracked-files=no")
        return commit + ("-dirty" if dirty else "")
    try:
        return f"gopre {metadata.version('gopre')}"
    except metadata.PackageNotFoundError:
        return "unknown"


def stale_versions(finished: dict[str, str | None], current: str) -> dict[str, int]:
    """Of the finished jobs (config hash -> code version), how many each older version made."""
    counts: dict[str, int] = {}
    for version in finished.values():
        if version != current:
            key = version or "unrecorded"
            counts[key] = counts.get(key, 0) + 1
    return counts
