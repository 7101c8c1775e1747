"""Paired old-vs-new final PSNR of two runs of the same study, from their reports' runs.csv.

    python tools/compare_revisions.py OLD/runs.csv NEW/runs.csv
    (the science study before the fidelity fixes: git show 3a7e471:reports/science/before_fidelity/runs.csv)

A pair is one (method, scene, seed, setting) FINISHED in both. Prints a Markdown table per
(scene, setting, method): pairs, mean old, mean new, mean and range of new - old; and the methods'
order within each (scene, setting) before and after. Methods or cells present in one file only
are listed, not compared.
"""

from __future__ import annotations

import argparse
import sys

import pandas as pd

KEYS = ["scene", "setting", "method", "seed"]


def finished(path: str) -> pd.DataFrame:
    frame = pd.read_csv(path)
    missing = sorted(set(KEYS + ["psnr", "status"]) - set(frame.columns))
    if missing:
        raise SystemExit(f"{path}: missing columns {missing}")
    return frame[frame["status"] == "FINISHED"][KEYS + ["psnr"]]


def paired(old: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    both = old.merge(new, on=KEYS, suffixes=("_old", "_new"))
    both["delta"] = both["psnr_new"] - both["psnr_old"]
    return both


def table(both: pd.DataFrame) -> str:
    rows = ["| scene | setting | method | pairs | old PSNR | new PSNR | new − old (min, max) |",
            "|---|---|---|---|---|---|---|"]
    grouped = both.groupby(["scene", "setting", "method"], sort=True)
    for (scene, setting, method), g in grouped:
        rows.append(f"| {scene} | {setting} | {method} | {len(g)} | {g.psnr_old.mean():.2f} | "
                    f"{g.psnr_new.mean():.2f} | {g.delta.mean():+.2f} ({g.delta.min():+.2f}, "
                    f"{g.delta.max():+.2f}) |")
    return "\n".join(rows)


def orders(both: pd.DataFrame) -> str:
    lines = []
    for (scene, setting), g in both.groupby(["scene", "setting"], sort=True):
        means = g.groupby("method")[["psnr_old", "psnr_new"]].mean()
        old = " > ".join(means["psnr_old"].sort_values(ascending=False).index)
        new = " > ".join(means["psnr_new"].sort_values(ascending=False).index)
        lines.append(f"- {scene}, {setting}: before {old}; after {new}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("old")
    parser.add_argument("new")
    args = parser.parse_args(argv)
    old, new = finished(args.old), finished(args.new)
    both = paired(old, new)
    if both.empty:
        print("no (method, scene, seed, setting) finished in both files", file=sys.stderr)
        return 1
    print(table(both))
    print()
    print(orders(both))
    only_old = sorted(set(old.method) - set(new.method))
    only_new = sorted(set(new.method) - set(old.method))
    if only_old or only_new:
        print(f"\nmethods in the old file only: {only_old or 'none'}; in the new file only: {only_new or 'none'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
