"""Per-module mutation score from mutmut's result files (mutants/**/*.py.meta).

    .venv/bin/python tools/mutation_summary.py              # after `make mutate`
    .venv/bin/python tools/mutation_summary.py --survivors  # and each survivor's changed line

Score = killed / (killed + survived + timeout + suspicious); mutants in functions that no selected
test calls ("no tests") are counted separately, not in the score.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

KILLED, SURVIVED, NO_TESTS = {1, 3, 37}, {0}, {5, 33}


def results(root: Path = Path("mutants")):
    """Yield (module path, {mutant name: exit code or None}) from each result file."""
    for meta in sorted(root.rglob("*.py.meta")):
        yield str(meta.relative_to(root))[:-len(".meta")], json.loads(meta.read_text())["exit_code_by_key"]


def summary(root: Path = Path("mutants")) -> list[dict]:
    rows = []
    for module, codes in results(root):
        counts = Counter("killed" if c in KILLED else "survived" if c in SURVIVED else
                         "no tests" if c in NO_TESTS else "not checked" if c is None else "other"
                         for c in codes.values())
        tested = counts["killed"] + counts["survived"] + counts["other"]
        rows.append({"module": module, **counts,
                     "score": round(counts["killed"] / tested, 3) if tested else None})
    return rows


def survivors(root: Path = Path("mutants")) -> list[str]:
    """Names of the surviving mutants, module by module."""
    return [name for _, codes in results(root) for name in sorted(k for k, c in codes.items() if c in SURVIVED)]


def changed_lines(name: str) -> str:
    """The survivor's diff as '- old / + new' lines (``mutmut show``)."""
    diff = subprocess.run([sys.executable, "-m", "mutmut", "show", name], capture_output=True,
                          text=True).stdout.splitlines()
    return "\n".join(line for line in diff if line[:1] in "-+" and line[:3] not in ("---", "+++"))


def main() -> int:
    rows = summary()
    if not rows:
        print("no mutmut results under mutants/ (run `make mutate` first)", file=sys.stderr)
        return 1
    print("| module | killed | survived | other | no tests | not checked | score |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['module']} | {r.get('killed', 0)} | {r.get('survived', 0)} | {r.get('other', 0)} | "
              f"{r.get('no tests', 0)} | {r.get('not checked', 0)} | {r['score']} |")
    if "--survivors" in sys.argv[1:]:
        for name in survivors():
            print(f"\n{name}\n{changed_lines(name)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
