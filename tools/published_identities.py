"""Which published reports average unlike things: for every reports/**/runs.csv, the rows (method,
setting) whose finished runs come from more than one code version or (where recorded) more than one
data fingerprint per scene. A report made after data identity refuses such rows itself
(pipeline.report.identity); this lists the ones published before it.

    python tools/published_identities.py [reports]
"""

from __future__ import annotations

import csv
import sys
from collections import defaultdict
from pathlib import Path


def mixed(path: Path) -> list[str]:
    rows = [r for r in csv.DictReader(open(path)) if r.get("status") == "FINISHED"]
    found = []
    for column, key in (("code_version", ("method", "setting")), ("data_fingerprint", ("method", "setting", "scene"))):
        if not rows or column not in rows[0]:
            continue
        seen = defaultdict(set)
        for r in rows:
            seen[tuple(r.get(k, "") for k in key)].add(r[column] or "not recorded")
        found += [f"{'/'.join(k for k in group if k)}: {column} {', '.join(sorted(values))}"
                  for group, values in seen.items() if len(values) > 1]
    return found


def main(argv=None) -> int:
    root = Path((argv or sys.argv[1:] or ["reports"])[0])
    bad = 0
    for path in sorted(root.rglob("runs.csv")):
        rows = mixed(path)
        bad += bool(rows)
        recorded = "data fingerprint recorded" if "data_fingerprint" in open(path).readline() else "no data fingerprint"
        print(f"{path}: {'MIXED ' + str(len(rows)) + ' row(s), e.g. ' + rows[0] if rows else 'one code version per row'} ({recorded})")
    print(f"{bad} report(s) with rows that mix identities")
    return 0


if __name__ == "__main__":
    sys.exit(main())
