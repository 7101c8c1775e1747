"""The same episodes under two settings, paired seed by seed, when the first setting's sweep folder is
gone but its published report is here: per method, the mean of (other − baseline) final PSNR over the
seeds both finished, its 95% BCa bootstrap interval (the reports' own, ``pipeline.report.stats``) and
the seeds the other setting is higher / lower on. ``gopre-report A B --by-sweep`` does this when both
folders exist.

    python tools/paired_settings.py reports/paper/table2_goal_bonsai_restaged/runs.csv \
        outputs/dips_nodensify_5seeds --scene bonsai

A pair is the same scene's data: each side's data fingerprints must be one and the same (runs.csv's
``data_fingerprint`` column, the records' on the other side), else nothing is printed and the exit
status is 2, naming both.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from pipeline.report.stats import TIE_DB, bootstrap_interval


def finished(source: Path, scene: str) -> pd.DataFrame:
    """The finished final rows of ``scene`` from a runs.csv or a sweep folder's records."""
    frame = (pd.read_csv(source) if source.suffix == ".csv"
             else pd.read_parquet(source / "records.parquet").query("kind == 'final'"))
    if "status" in frame:
        frame = frame[frame["status"] == "FINISHED"]
    return frame[frame["scene"] == scene]


def fingerprints(frame: pd.DataFrame) -> set[str]:
    if "data_fingerprint" not in frame:
        return set()
    return {str(f) for f in frame["data_fingerprint"].dropna() if str(f)}


def paired_table(baseline: pd.DataFrame, other: pd.DataFrame) -> list[str]:
    base = baseline.groupby(["method", "seed"])["psnr"].mean()
    new = other.groupby(["method", "seed"])["psnr"].mean()
    lines = ["| method | baseline | other | other − baseline (95% BCa) | higher / lower / level |",
             "|---|---|---|---|---|"]
    pairs = pd.concat([base, new], axis=1, keys=["base", "new"]).dropna()  # (method, seed) both finished
    for method in dict.fromkeys(other["method"]):
        if method not in pairs.index.get_level_values(0):
            lines.append(f"| {method} | n/a | {new[method].mean():.2f} | no pairs | |")
            continue
        both = pairs.loc[method]
        diff = (both["new"] - both["base"]).to_numpy(dtype=float)
        low, high = bootstrap_interval(diff)
        higher, lower = int((diff > TIE_DB).sum()), int((diff < -TIE_DB).sum())
        lines.append(f"| {method} | {both['base'].mean():.2f} | {both['new'].mean():.2f} | "
                     f"{diff.mean():+.2f} [{low:+.2f}, {high:+.2f}] (n = {diff.size}) | "
                     f"{higher} / {lower} / {diff.size - higher - lower} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("baseline", type=Path, help="the baseline setting: a runs.csv or a sweep folder")
    parser.add_argument("other", type=Path, help="the other setting: a runs.csv or a sweep folder")
    parser.add_argument("--scene", required=True)
    args = parser.parse_args(argv)
    baseline, other = finished(args.baseline, args.scene), finished(args.other, args.scene)
    for name, frame in ((args.baseline, baseline), (args.other, other)):
        if frame.empty:
            print(f"{name}: no finished episode of scene {args.scene!r}")
            return 2
    ours, theirs = fingerprints(baseline), fingerprints(other)
    if len(ours) != 1 or ours != theirs:
        print(f"not the same data: {args.baseline} has data fingerprint(s) {sorted(ours) or 'none recorded'}, "
              f"{args.other} has {sorted(theirs) or 'none recorded'}")
        return 2
    print("\n".join(paired_table(baseline, other)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
