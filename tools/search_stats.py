"""How an off-pool sweep's pose search went (issue 28), from its records:

    .venv/bin/python tools/search_stats.py outputs/continuous [--method gopre_search]

Per protocol: the rounds, the share whose searched pose beat the pool's best candidate (and was
captured), the mean relative score gain over the pool's best in those rounds, and the selection
time per round (CPU and wall) of every method."""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep", type=Path)
    parser.add_argument("--method", default="gopre_search")
    args = parser.parse_args(argv)
    frame = pd.read_parquet(args.sweep / "records.parquet")
    if "search_taken" not in frame:
        print(f"{args.sweep}: no round of this sweep searched off the pool")
        return 1
    rounds = frame[(frame["kind"] == "round") & (frame["method"] == args.method) & frame["search_taken"].notna()]
    print("| protocol | rounds | searched pose taken | mean score gain over the pool's best (taken rounds) |")
    print("|---|---|---|---|")
    for protocol, part in rounds.groupby("protocol"):
        taken = part[part["search_taken"] == "search"]
        gain = ((taken["search_best_pool_score"] - taken["search_score"]) / taken["search_best_pool_score"]).mean()
        print(f"| {protocol} | {len(part)} | {len(taken)} ({len(taken) / len(part):.0%}) | {gain:.2%} |")
    final = frame[frame["kind"] == "final"]
    times = final.groupby(["protocol", "method"])[["selection_cpu_seconds", "selection_seconds"]].mean()
    print("\n| protocol | method | selection CPU s / round | selection wall s / round |\n|---|---|---|---|")
    for (protocol, method), row in times.iterrows():
        print(f"| {protocol} | {method} | {row['selection_cpu_seconds']:.2f} | {row['selection_seconds']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
