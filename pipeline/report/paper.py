"""A sweep beside the GO-PRE paper's own table: the paper's numbers and ours, the two orderings and
their rank agreement (Kendall's tau), and one verdict line per claim the paper's text makes about
that table (reproduced / not reproduced / not testable at this scale), with the paired interval.

The paper's numbers live in ``paper_tables.yaml`` (copied from the paper's .tex, checked against it
by a test). A sweep maps to a paper table by its name (``table1_global`` ...) or by an explicit
table id (``gopre-report outputs/science --paper table2_goal``: the study's goal-protocol runs
beside Table 2). Absolute numbers are not comparable at CPU scale (64 px, 2-5k iterations instead
of 1066 x 1600 and 30k): the comparison that means something is the ordering and the paired gaps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from scipy.stats import kendalltau

from pipeline.report.rows import finished
from pipeline.report.stats import MIN_PAIRS, bootstrap_interval

PAPER_TABLES = Path(__file__).with_name("paper_tables.yaml")
METRIC_LABELS = {"psnr": "PSNR", "ssim": "SSIM", "lpips": "LPIPS", "per_candidate_ms": "per-cand. ms",
                 "selection_seconds": "round s", "peak_rss_mb": "peak MB"}
SCALE_NOTE = ("Absolute numbers differ from the paper's by design (CPU scale: 64 px, 2-5k iterations, "
              "10k Gaussians; the paper: 1066 x 1600 px, 30k iterations, a GPU); compare the orderings "
              "and the paired gaps. Our SSIM is 3DGS's (zero-padded windows, the full-image mean), as the "
              "paper's, on float renders (3DGS scores 8-bit PNGs); our memory is the process's peak "
              "RSS, the paper's is GPU memory; our times come from jobs that shared 2 cores with "
              "other jobs of the sweep.")


@dataclass(frozen=True)
class Claim:
    text: str
    kind: str                       # outperforms | gap | largest_drop | within | no_gain | cheaper | decreasing | cross_table
    row: str | None = None          # our method name or setting string
    against: tuple[str, ...] | str = ()
    reference: str | None = None
    paper_gap: float | None = None
    bound: float | None = None
    metric: str = "psnr"
    reason: str = ""


@dataclass(frozen=True)
class PaperTable:
    id: str
    paper: str
    protocol: str
    rows_by: str                    # "method" or "setting"
    rows: dict[str, str]            # paper row label -> our method / setting
    metrics: list[str]
    values: dict[str, dict[str, list[float]]]  # paper dataset -> paper row label -> one per metric
    claims: list[Claim] = field(default_factory=list)


METRIC_UNITS = {"psnr": "dB", "per_candidate_ms": "ms", "peak_rss_mb": "MB", "ssim": "", "lpips": ""}


def unit_of(metric: str) -> str:
    """The unit a paired gap of ``metric`` is printed in."""
    return METRIC_UNITS.get(metric, "")


@dataclass(frozen=True)
class Gap:
    """row - reference over the pairs both finished (for a lower-is-better metric still row -
    reference: a negative time gap means the row is cheaper)."""
    n: int
    mean: float
    low: float
    high: float

    def text(self, unit: str = "dB") -> str:
        unit = f" {unit}" if unit else ""
        interval = f"[{self.low:+.2f}, {self.high:+.2f}]" if self.n >= 2 else "[n/a]"  # 1 pair: no interval
        return f"{self.mean:+.2f}{unit} {interval}, n = {self.n}"


@dataclass(frozen=True)
class Verdict:
    claim: Claim
    outcome: str                    # reproduced | not reproduced | not testable at this scale
    detail: str


def load_paper_tables(path: Path = PAPER_TABLES) -> tuple[dict[str, list[str]], dict[str, PaperTable]]:
    """(paper dataset -> its scenes, table id -> PaperTable) from the data file."""
    raw = yaml.safe_load(path.read_text())
    tables = {}
    for tid, t in raw["tables"].items():
        claims = [Claim(**{**c, "against": tuple(c["against"]) if isinstance(c.get("against"), list)
                            else c.get("against", ())}) for c in t.get("claims", [])]
        tables[tid] = PaperTable(tid, t["paper"], t["protocol"], t["rows_by"], dict(t["rows"]),
                                 list(t["metrics"]), t["values"], claims)
        for dataset, rows in t["values"].items():
            for label, numbers in rows.items():
                if label not in t["rows"] or len(numbers) != len(t["metrics"]):
                    raise ValueError(f"{path}: {tid}/{dataset}/{label}: unknown row or wrong count")
    return raw["datasets"], tables


def paper_dataset(scene: str, datasets: dict[str, list[str]]) -> str | None:
    """The paper dataset a scene belongs to (lego -> Blender, bonsai -> Mip-NeRF360), else None."""
    for name, scenes in datasets.items():
        if scene in scenes:
            return name
    return None


def table_for(sweep: str, requested: str | None, tables: dict[str, PaperTable]) -> PaperTable:
    key = requested or sweep
    if key not in tables:
        raise ValueError(f"--paper: sweep {sweep!r} maps to no paper table; name one of "
                         f"{sorted(tables)} (gopre-report <sweep> --paper table1_global)")
    return tables[key]


def rows_of(final: pd.DataFrame, table: PaperTable, datasets: dict[str, list[str]]) -> pd.DataFrame:
    """The finished episodes of ``final`` under the table's protocol, with ``row`` (our method or
    setting) and ``paper_dataset`` columns; scenes outside the paper's datasets are kept (None)."""
    part = final[final["protocol"] == table.protocol].copy()
    part["setting"] = part["setting"].fillna("")
    by_method = table.rows_by == "method"
    part["row"] = part["method"] if by_method else part["setting"].map(_setting_row)
    # the protocol is fixed by the table, so a setting that only names it pairs with no setting
    # (a study's "protocol.kind=global" rows with a preset's rows, reported together)
    part["pair"] = part["setting"].map(_other_axes) if by_method else part["method"]
    part["paper_dataset"] = part["scene"].map(lambda s: paper_dataset(s, datasets))
    return part


def _other_axes(setting: str) -> str:
    """The setting without its ``protocol.kind=`` part ('' when nothing else is left)."""
    return ",".join(p for p in str(setting).split(",") if p and not p.startswith("protocol.kind="))


def _setting_row(setting: str) -> str:
    """The sweep-axis part of a setting that names a paper row (``protocol.probes=0.125``)."""
    return ",".join(p for p in str(setting).split(",") if not p.startswith("protocol.kind=")) or setting


def paired_gap(part: pd.DataFrame, row: str, reference: str, metric: str) -> Gap | None:
    """row - reference on ``metric`` over the pairs both finished: the same scene, seed and
    ``pair`` (the other axis: the setting when rows are methods, the method when rows are
    settings); None when there is no pair."""
    data = part.dropna(subset=[metric])
    table = data.pivot_table(index=["dataset", "scene", "seed", "pair"], columns="row", values=metric,
                             aggfunc="mean")
    if row not in table or reference not in table:
        return None
    both = table[[row, reference]].dropna()
    if both.empty:
        return None
    d = (both[row] - both[reference]).to_numpy(dtype=float)
    low, high = bootstrap_interval(d)
    return Gap(int(d.size), float(d.mean()), low, high)


def judge(claim: Claim, part: pd.DataFrame, rows_run: list[str]) -> Verdict:
    """One claim -> reproduced / not reproduced / not testable at this scale, with its numbers."""
    untestable = "not testable at this scale"
    if claim.kind == "cross_table":
        return Verdict(claim, untestable, claim.reason)
    if claim.kind == "decreasing":
        means = [part.loc[part["row"] == r, claim.metric].mean() for r in rows_run]
        if len(means) < 2 or any(np.isnan(means)):
            return Verdict(claim, untestable, f"fewer than two rows with {claim.metric}")
        ok = all(a > b for a, b in zip(means, means[1:]))
        return Verdict(claim, "reproduced" if ok else "not reproduced",
                       "means in row order: " + ", ".join(f"{m:.3g}" for m in means))
    if claim.row not in rows_run:
        return Verdict(claim, untestable, f"{claim.row} did not run in this sweep")
    if claim.kind == "outperforms":
        return _outperforms(claim, part, rows_run)
    ref = claim.reference
    if ref not in rows_run:
        return Verdict(claim, untestable, f"{ref} did not run in this sweep")
    gap = paired_gap(part, claim.row, ref, claim.metric)
    if gap is None or gap.n < MIN_PAIRS:
        n = 0 if gap is None else gap.n
        return Verdict(claim, untestable, f"{n} pair(s) of {claim.row} and {ref} (a verdict needs "
                       f"{MIN_PAIRS})" + (f"; so far {gap.text(unit_of(claim.metric))}" if gap else ""))
    if claim.kind == "gap":
        ok = gap.high < 0 if claim.paper_gap < 0 else gap.low > 0
        return Verdict(claim, "reproduced" if ok else "not reproduced",
                       f"{claim.row} - {ref}: ours {gap.text()}, the paper {claim.paper_gap:+.2f} dB")
    if claim.kind == "largest_drop":
        drops = {r: paired_gap(part, r, ref, "psnr") for r in rows_run if r != ref}
        drops = {r: g for r, g in drops.items() if g is not None}
        worst = min(drops, key=lambda r: drops[r].mean)
        ok = worst == claim.row and gap.high < 0
        return Verdict(claim, "reproduced" if ok else "not reproduced",
                       f"{claim.row} - {ref}: {gap.text()} (paper {claim.paper_gap:+.2f} dB); the largest "
                       f"drop is {worst}'s ({drops[worst].mean:+.2f} dB)")
    if claim.kind == "within":
        ok = gap.low >= -claim.bound
        return Verdict(claim, "reproduced" if ok else "not reproduced",
                       f"{claim.row} - {ref}: {gap.text()}; bound -{claim.bound:.2f} dB")
    if claim.kind == "no_gain":
        ok = gap.low <= 0
        return Verdict(claim, "reproduced" if ok else "not reproduced", f"{claim.row} - {ref}: {gap.text()}")
    if claim.kind == "cheaper":
        ok = gap.high < 0
        return Verdict(claim, "reproduced" if ok else "not reproduced",
                       f"{claim.row} - {ref} ({claim.metric}): {gap.text(unit_of(claim.metric))}")
    raise ValueError(f"paper_tables.yaml: unknown claim kind {claim.kind!r}")


def _outperforms(claim: Claim, part: pd.DataFrame, rows_run: list[str]) -> Verdict:
    others = [r for r in rows_run if r != claim.row] if claim.against == "all" else \
        [r for r in claim.against if r in rows_run]
    missing = [] if claim.against == "all" else [r for r in claim.against if r not in rows_run]
    if not others:
        return Verdict(claim, "not testable at this scale", "no other method ran")
    gaps = {r: paired_gap(part, claim.row, r, claim.metric) for r in others}
    few = [r for r, g in gaps.items() if g is None or g.n < MIN_PAIRS]
    parts = [f"vs {r} {g.text()}" for r, g in gaps.items() if g is not None]
    tail = (f"; not run: {', '.join(missing)}" if missing else "")
    if few:
        return Verdict(claim, "not testable at this scale",
                       f"fewer than {MIN_PAIRS} pairs against {', '.join(few)}; " + "; ".join(parts) + tail)
    lost = [r for r, g in gaps.items() if g.low <= 0]
    outcome = "not reproduced" if lost else "reproduced"
    head = f"interval not above 0 against {', '.join(lost)}: " if lost else ""
    return Verdict(claim, outcome, head + "; ".join(parts) + tail)


def ordering(values: dict[str, float], higher_is_better: bool) -> list[str]:
    return sorted(values, key=lambda r: -values[r] if higher_is_better else values[r])


def rank_agreement(paper: dict[str, float], ours: dict[str, float]) -> tuple[float, int]:
    """Kendall's tau between the paper's and our values over the rows both have (nan below 3)."""
    common = [r for r in paper if r in ours and not np.isnan(ours[r])]
    if len(common) < 3:
        return float("nan"), len(common)
    tau = kendalltau([paper[r] for r in common], [ours[r] for r in common]).statistic
    return float(tau), len(common)


def compare(final: pd.DataFrame, table: PaperTable, datasets: dict[str, list[str]]) -> str:
    """The side-by-side Markdown: numbers, orderings, Kendall's tau, claims."""
    part = rows_of(final, table, datasets)
    ours_label = {v: k for k, v in table.rows.items()}
    lines = [f"## Beside the paper: {table.paper}", "", SCALE_NOTE, ""]
    if part.empty:
        return "\n".join(lines + [f"No finished episode of this sweep ran the {table.protocol} protocol.", ""])
    rows_run = [r for r in table.rows.values() if r in set(part["row"])]
    extra = [r for r in dict.fromkeys(part["row"]) if r not in table.rows.values()]
    outside = sorted(set(part.loc[part["paper_dataset"].isna(), "scene"]))
    for dataset in table.values:
        here = part[part["paper_dataset"] == dataset]
        if here.empty:
            lines += [f"### {dataset}: not run (no scene of this dataset in the sweep)", ""]
            continue
        lines += _dataset_section(table, dataset, here, ours_label, extra)
    if outside:
        lines += [f"Scenes outside the paper's datasets ({', '.join(outside)}) are in the main report only.", ""]
    lines += ["### The paper's claims about this table", "",
              "| claim (paper) | verdict | ours |", "|---|---|---|"]
    for claim in table.claims:
        v = judge(claim, part[part["paper_dataset"].notna()], rows_run)
        lines.append(f"| {claim.text} | **{v.outcome}** | {v.detail} |")
    return "\n".join(lines + [""])


def _dataset_section(table: PaperTable, dataset: str, here: pd.DataFrame, ours_label: dict[str, str],
                     extra: list[str]) -> list[str]:
    scenes = sorted(set(here["scene"]))
    seeds = sorted(set(here["seed"]))
    lines = [f"### {dataset} (ours: {', '.join(scenes)}; seeds {seeds})", ""]
    head = ["row"] + [f"{METRIC_LABELS[m]} {who}" for m in table.metrics for who in ("paper", "ours")]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    paper_rows = table.values[dataset]
    ours = {m: here.groupby("row")[m].agg(["mean", "std", "count"]) for m in table.metrics if m in here}
    for label, row in list(table.rows.items()) + [(f"{r} (not in the paper)", r) for r in extra]:
        cells = [label]
        for i, m in enumerate(table.metrics):
            paper_value = paper_rows.get(label, [None] * len(table.metrics))[i]
            cells.append("—" if paper_value is None else f"{paper_value:g}")
            cells.append(_our_cell(ours.get(m), row))
        lines.append("| " + " | ".join(cells) + " |")
    psnr_ours = {r: float(here.loc[here["row"] == r, "psnr"].mean()) for r in table.rows.values()
                 if (here["row"] == r).any()}
    psnr_paper = {table.rows[label]: v[0] for label, v in paper_rows.items()}
    tau, n = rank_agreement(psnr_paper, psnr_ours)
    paper_order = [r for r in ordering(psnr_paper, True) if r in psnr_ours]
    lines += ["", f"PSNR ordering, the paper: {' > '.join(paper_order)}; ours: "
              f"{' > '.join(ordering(psnr_ours, True))}; Kendall's tau = "
              + (f"{tau:+.2f} over {n} rows" if not np.isnan(tau) else f"n/a ({n} common rows)"), ""]
    return lines


def _our_cell(stats: pd.DataFrame | None, row: str) -> str:
    if stats is None or row not in stats.index:
        return "not run"
    if stats.loc[row, "count"] == 0:
        return "unavailable"  # e.g. LPIPS without its pretrained weights
    mean, std, n = stats.loc[row, "mean"], stats.loc[row, "std"], int(stats.loc[row, "count"])
    digits = 2 if abs(mean) >= 10 else 3
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if n > 1 else "") + f" (n={n})"


def paper_report(frame: pd.DataFrame, requested: str | None = None,
                 path: Path = PAPER_TABLES) -> str:
    """The Markdown comparison of a sweep's records with the paper table it maps to."""
    datasets, tables = load_paper_tables(path)
    sweep = str(frame["sweep"].iloc[0])
    table = table_for(sweep, requested, tables)
    return compare(finished(frame, "final"), table, datasets)
