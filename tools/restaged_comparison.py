"""Old beside new for one scene whose data changed: per method, the mean final PSNR (and its std over
seeds) of a published report's runs (its runs.csv) and of a new sweep's records, with the difference.

    git show 3a7e471:reports/paper/table2_goal_5seeds/runs.csv > /tmp/old.csv
    python tools/restaged_comparison.py /tmp/old.csv \
        outputs/table2_goal_bonsai --scene bonsai [--seeds 0,1,2,3,4] [--setting protocol.kind=goal]

Prints a markdown table; the old and the new are different data (the scene was re-staged), so the
difference is of means, never of pairs. Methods missing on either side are listed with n/a.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd


def means(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.groupby("method", sort=False)["psnr"].agg(["mean", "std", "count"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("old_runs", type=Path, help="the published report's runs.csv")
    parser.add_argument("new", type=Path, help="the new sweep folder (records.parquet) or its runs.csv")
    parser.add_argument("--scene", required=True)
    parser.add_argument("--seeds", default=None, help="only these seeds, e.g. 0,1,2")
    parser.add_argument("--setting", default=None,
                        help="only the runs of this setting (the `setting` column of a sweep over settings, "
                             "e.g. protocol.kind=goal); without it a sweep of several settings is refused")
    args = parser.parse_args(argv)
    old = pd.read_csv(args.old_runs)
    new = (pd.read_csv(args.new) if args.new.suffix == ".csv"
           else pd.read_parquet(args.new / "records.parquet").query("kind == 'final'"))
    frames = []
    for label, frame in (("old", old), ("new", new)):
        part = frame[(frame["scene"] == args.scene) & (frame["status"] == "FINISHED")]
        if args.seeds:
            part = part[part["seed"].isin([int(s) for s in args.seeds.split(",")])]
        settings = set(part["setting"].fillna("")) if "setting" in part else {""}
        if args.setting is not None:
            part = part[part["setting"] == args.setting]
        elif len(settings) > 1:
            raise SystemExit(f"{label}: runs of {len(settings)} settings ({', '.join(sorted(settings))}); "
                             "name one with --setting")
        frames.append(means(part))
    old_m, new_m = frames
    methods = list(dict.fromkeys(list(old_m.index) + list(new_m.index)))
    lines = ["| method | old (folded) | new (re-staged) | new − old |", "|---|---|---|---|"]

    def cell(m, table):
        if m not in table.index:
            return "n/a"
        r = table.loc[m]
        spread = f" ± {r['std']:.2f}" if r["count"] > 1 else ""
        return f"{r['mean']:.2f}{spread} ({int(r['count'])})"
    for m in methods:
        diff = (f"{new_m.loc[m, 'mean'] - old_m.loc[m, 'mean']:+.2f}" if m in old_m.index and m in new_m.index else "n/a")
        lines.append(f"| {m} | {cell(m, old_m)} | {cell(m, new_m)} | {diff} |")
    for name, table in (("old", old_m), ("new", new_m)):
        order = table["mean"].sort_values(ascending=False).index.tolist()
        lines.append(f"\n{name} ordering: {' > '.join(order)}")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
