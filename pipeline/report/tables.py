"""Tables from a sweep's records: Markdown and LaTeX (booktabs), best / second / third marked;
and paired-comparison tables against a reference method (``PairedTable``).

Aggregation: per (method, dataset, setting, seed) the mean over scenes, then mean +- std over
seeds (std shown only when there are several seeds). Missing cells (a dataset not run, LPIPS
unavailable) print as "n/a", never as zeros. Ranks are computed per column on the means, in the
metric's direction (LPIPS and times: lower is better).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from pipeline.report.power import MAX_SEEDS
from pipeline.report.stats import verdict

LOWER_IS_BETTER = {"lpips", "per_candidate_ms", "selection_seconds", "selection_cpu_seconds",
                   "ause", "wall_seconds", "unc_ause_mae_max", "unc_ause_mae_start", "unc_ause_rmse_max",
                   "unc_ause_rmse_start", "unc_ause_dssim_max", "unc_ause_dssim_start", "unc_nll", "unc_auce",
                   "path_length", "depth_abs_rel", "depth_rmse", "depth_ause_abs_rel"}
# the final model's pixel-level uncertainty (pipeline.eval.model_uncertainty; records columns unc_*)
UNCERTAINTY_METRICS = ["unc_ause_mae_max", "unc_ause_mae_start", "unc_ause_rmse_max", "unc_ause_dssim_start",
                       "unc_nll", "unc_auce", "unc_pearson", "unc_spearman", "depth_abs_rel", "depth_rmse",
                       "depth_ause_abs_rel"]
METRIC_LABELS = {"psnr": "PSNR", "psnr_auc": "PSNR area", "ssim": "SSIM", "ssim_skimage": "SSIM (skimage)", "lpips": "LPIPS",
                 "per_candidate_ms": "Per-cand. (ms)",
                 "selection_seconds": "Selection (s)", "selection_cpu_seconds": "Selection CPU (s / round)",
                 "ause": "AUSE", "wall_seconds": "Wall (s)",
                 "unc_ause_mae_max": "AUSE MAE (max-norm.)", "unc_ause_mae_start": "AUSE MAE (start-norm.)",
                 "unc_ause_rmse_max": "AUSE RMSE (max-norm.)", "unc_ause_dssim_start": "AUSE DSSIM (start-norm.)",
                 "unc_nll": "NLL", "unc_auce": "AUCE", "unc_pearson": "Pearson r", "unc_spearman": "Spearman ρ",
                 "path_length": "Camera path (pool diameters)", "depth_abs_rel": "Depth abs rel",
                 "depth_rmse": "Depth RMSE", "depth_ause_abs_rel": "Depth AUSE"}
DIGITS = {**{m: 3 for m in UNCERTAINTY_METRICS}, "unc_nll": 2, "path_length": 2, "psnr": 2, "psnr_auc": 2, "ssim": 3,
          "ssim_skimage": 3, "lpips": 3, "per_candidate_ms": 1, "selection_seconds": 2, "ause": 3,
          "wall_seconds": 0, "selection_cpu_seconds": 2}
MISSING = "n/a"


@dataclass
class Cell:
    mean: float | None
    std: float | None = None
    n: int = 0
    rank: int | None = None   # 1 best, 2 second, 3 third


@dataclass
class Table:
    title: str
    row_label: str
    rows: list[str]
    columns: list[tuple[str, str]]           # (group, metric)
    cells: dict[tuple[str, tuple[str, str]], Cell]
    notes: list[str] = field(default_factory=list)


def _aggregate(final: pd.DataFrame, row_key: str, group_key: str | None, metric: str) -> dict:
    if metric not in final or final[metric].isna().all():
        return {}
    keys = [row_key] + ([group_key] if group_key else [])
    data = final.dropna(subset=[metric])
    per_seed = data.groupby(keys + ["seed"], dropna=False)[metric].mean().reset_index()
    out = {}
    for key, part in per_seed.groupby(keys, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        values = part[metric].to_numpy(dtype=float)
        std = float(np.std(values, ddof=1)) if len(values) > 1 else None
        out[(key[0], key[1] if group_key else "")] = Cell(float(values.mean()), std, len(values))
    return out


def _rank(cells: dict, rows: list[str], column: tuple[str, str]) -> None:
    """Ranks on the values as printed: two cells that print the same number share a mark."""
    present = [(r, cells[(r, column)]) for r in rows if (r, column) in cells and cells[(r, column)].mean is not None]
    sign = 1 if column[1] in LOWER_IS_BETTER else -1
    digits = DIGITS.get(column[1], 3)
    distinct = sorted({round(sign * c.mean, digits) for _, c in present})
    for _, cell in present:
        place = distinct.index(round(sign * cell.mean, digits)) + 1
        cell.rank = place if place <= 3 and len(present) > 1 else None


def build_table(final: pd.DataFrame, title: str, row_key: str, group_key: str | None,
                metrics: list[str], row_order: list[str] | None = None) -> Table:
    """Rows = values of ``row_key``; columns = (group, metric) for each group value and metric."""
    rows = row_order or list(dict.fromkeys(final[row_key]))
    groups = list(dict.fromkeys(final[group_key])) if group_key else [""]
    columns = [(g, m) for g in groups for m in metrics]
    cells = {}
    for metric in metrics:
        for (row, group), cell in _aggregate(final, row_key, group_key, metric).items():
            cells[(row, (group, metric))] = cell
    for column in columns:
        _rank(cells, rows, column)
    notes = []
    if "lpips" in metrics and not any(c[1] == "lpips" for (_, c) in cells):
        status = final["lpips_status"].dropna().unique() if "lpips_status" in final else []
        notes.append(lpips_note(str(status[0]) if len(status) else ""))
    return Table(title, row_key, rows, columns, cells, notes)


def lpips_note(status: str) -> str:
    """A sentence for a table note (never an exception's text): why the LPIPS cells are n/a."""
    if "disabled" in status:
        return "LPIPS disabled in the config (n/a)."
    return ("LPIPS unavailable: the optional lpips package or its pretrained weights are not "
            "installed, so its cells are n/a (never a number).")


def format_cell(cell: Cell | None, metric: str) -> str:
    if cell is None or cell.mean is None or (isinstance(cell.mean, float) and math.isnan(cell.mean)):
        return MISSING
    d = DIGITS.get(metric, 3)
    text = f"{cell.mean:.{d}f}"
    if cell.std is not None:
        text += f" ± {cell.std:.{d}f}"
    return text


def to_markdown(table: Table) -> str:
    groups = list(dict.fromkeys(g for g, _ in table.columns))
    header = [table.row_label] + [f"{g} {METRIC_LABELS.get(m, m)}".strip() for g, m in table.columns]
    lines = [f"### {table.title}", "", "| " + " | ".join(header) + " |",
             "|" + "---|" * len(header)]
    marks = {1: ("**", "**"), 2: ("<ins>", "</ins>"), 3: ("_", "_")}  # as the LaTeX macros
    for row in table.rows:
        out = [str(row)]
        for column in table.columns:
            cell = table.cells.get((row, column))
            text = format_cell(cell, column[1])
            if cell is not None and cell.rank in marks and text != MISSING:
                left, right = marks[cell.rank]
                text = f"{left}{text}{right}"
            out.append(text)
        lines.append("| " + " | ".join(out) + " |")
    lines.append("")
    lines.append("Best in **bold**, second <ins>underlined</ins>, third in _italics_." + (
        f" Groups: {', '.join(groups)}." if groups != [""] else ""))
    lines += [f"Note: {n}" for n in table.notes]
    return "\n".join(lines) + "\n"


def _tex_escape(text: str) -> str:
    return (str(text).replace("\\", r"\textbackslash{}").replace("_", r"\_").replace("&", r"\&")
            .replace("%", r"\%").replace("#", r"\#"))


# A table wider than the text is scaled down to the text width (never an overfull line); one that
# fits is set at its natural size. Plain LaTeX + graphicx, so the file pastes into any paper.
FIT_OPEN = [r"\ifdefined\gopretablebox\else\newsavebox{\gopretablebox}\fi",
            r"\sbox{\gopretablebox}{%"]
FIT_CLOSE = [r"}%", r"\ifdim\wd\gopretablebox>\linewidth\resizebox{\linewidth}{!}{\usebox{\gopretablebox}}"
             r"\else\usebox{\gopretablebox}\fi"]


def tex_number(text: str) -> str:
    """A printed cell in math mode: a true minus sign and a math plus-minus ("-0.42 ± 0.10" ->
    "$-0.42 \\pm 0.10$"), the same in every table."""
    return "$" + text.replace(" ± ", r" \pm ") + "$"


def tex_notes(notes: list[str]) -> list[str]:
    """Notes under the tabular, each its own paragraph set to the text width (never on the
    tabular's line)."""
    if not notes:
        return []
    body = r" \\ ".join(f"Note: {_tex_escape(n)}" for n in notes)
    return [r"\par\smallskip", rf"\parbox{{\linewidth}}{{\footnotesize {body}}}"]


AREA_DEFINITION = ("PSNR area: the area under the PSNR-vs-views curve over the rounds divided by "
                   "its span of views, i.e. the curve's mean PSNR in dB")


def seeds_phrase(table: Table) -> str:
    """How the cells aggregate: mean ± std over the seeds, or single runs (no spread) when every
    cell holds one seed."""
    counts = {c.n for c in table.cells.values() if c is not None and c.mean is not None}
    if counts and max(counts) <= 1:
        return "one seed per cell (no spread)"
    if len(counts) == 1:
        return f"mean $\\pm$ std over {counts.pop()} seeds"
    return "mean $\\pm$ std over the seeds each cell has"


def latex_caption(table: Table) -> str:
    """What the table shows, not only the sweep's name: the metrics, how cells aggregate over
    seeds, what the marks mean and what "PSNR area" is when the table has it."""
    metrics = ", ".join(dict.fromkeys(METRIC_LABELS.get(m, m) for _, m in table.columns))
    area = f"; {AREA_DEFINITION}" if any(m == "psnr_auc" for _, m in table.columns) else ""
    return (f"{_tex_escape(table.title)}: {_tex_escape(metrics)} per {_tex_escape(table.row_label.lower())}, "
            f"{seeds_phrase(table)}; best in bold, second underlined, third in italics{area}")


def _tex_label(text: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in str(text).lower()).strip("-")[:60] or "table"


def to_latex(table: Table) -> str:
    groups = list(dict.fromkeys(g for g, _ in table.columns))
    per_group = len(table.columns) // max(len(groups), 1)
    arrows = {m: (r"$\downarrow$" if m in LOWER_IS_BETTER else r"$\uparrow$") for _, m in table.columns}
    lines = [r"% requires \usepackage{booktabs} and \usepackage{graphicx}",
             # a cell is math ($23.61 \pm 0.10$): \textbf and \textit do not reach it, \boldmath and
             # \mathit do (the marks are visible in the PDF: tests/test_report.py reads its fonts)
             r"\providecommand{\best}[1]{{\boldmath$#1$}}",
             r"\providecommand{\second}[1]{\underline{$#1$}}",
             r"\providecommand{\third}[1]{$\mathit{#1}$}",
             r"\begin{table}[t]", r"\centering", rf"\caption{{{latex_caption(table)}}}",
             rf"\label{{tab:{_tex_label(table.title)}}}",
             *FIT_OPEN, r"\begin{tabular}{l" + "c" * len(table.columns) + "}", r"\toprule"]
    if groups != [""]:
        lines.append(" & " + " & ".join(rf"\multicolumn{{{per_group}}}{{c}}{{{_tex_escape(g)}}}"
                                         for g in groups) + r" \\")
        lines.append("".join(rf"\cmidrule(lr){{{2 + i * per_group}-{1 + (i + 1) * per_group}}}"
                             for i in range(len(groups))))
    lines.append(_tex_escape(table.row_label) + " & " + " & ".join(
        f"{METRIC_LABELS.get(m, m)}{arrows[m]}" for _, m in table.columns) + r" \\")
    lines.append(r"\midrule")
    macro = {1: r"\best", 2: r"\second", 3: r"\third"}
    for row in table.rows:
        out = [_tex_escape(row)]
        for column in table.columns:
            cell = table.cells.get((row, column))
            text = format_cell(cell, column[1])
            text = MISSING if text == MISSING else tex_number(text)
            if cell is not None and cell.rank in macro and text != MISSING:
                text = f"{macro[cell.rank]}{{{text.strip('$')}}}"  # the macros set the math themselves
            out.append(text)
        lines.append(" & ".join(out) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", *FIT_CLOSE]
    lines += tex_notes(table.notes)
    lines.append(r"\end{table}")
    return "\n".join(lines) + "\n"


@dataclass
class PairedTable:
    """Paired differences against a reference, one row per method, one column block per metric.

    rows: {method: {metric: PairedComparison}}."""

    title: str
    reference: str
    metrics: list[str]
    rows: dict[str, dict]
    notes: list[str] = field(default_factory=list)


def _signed(x: float, d: int) -> str:
    return f"{x:+.{d}f}"


def _p_value(p: float | None) -> str:
    return MISSING if p is None else (f"{p:.3f}" if p >= 0.001 else "<0.001")


def _effect(c) -> str:
    """'d_z (seeds for 80% power)': '+1.32 (7)', '+0.01 (> 10000)', or n/a without a spread."""
    if c.effect_size is None:
        return MISSING
    seeds = str(c.seeds_needed) if c.seeds_needed is not None else f"> {MAX_SEEDS}"
    return f"{_signed(c.effect_size, 2)} ({seeds})"


def _paired_cells(c, metric: str) -> list[str]:
    """[difference with its interval, W/L/T, Wilcoxon p, effect size (seeds needed), verdict]."""
    if c is None:
        return [MISSING, MISSING, MISSING, MISSING, MISSING]
    d = DIGITS.get(metric, 2)
    interval = f"[{_signed(c.low, d)}, {_signed(c.high, d)}]" if c.n >= 2 else f"[{MISSING}]"  # 1 pair: no interval
    return [f"{_signed(c.mean_difference, d)} {interval}",
            f"{c.wins}/{c.losses}/{c.ties}", _p_value(c.wilcoxon_p), _effect(c), verdict(c)]


PAIRED_LABELS = {"psnr": "final PSNR", "psnr_auc": "PSNR-vs-views area"}


def paired_to_markdown(table: PairedTable) -> str:
    header = ["method", "pairs"]
    for m in table.metrics:
        label = PAIRED_LABELS.get(m, m)
        header += [f"Δ {label} (dB) [95% CI]", f"{label} W/L/T", f"{label} Wilcoxon p",
                   f"{label} d_z (seeds for 80% power)", f"{label} verdict"]
    lines = [f"### {table.title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method, by_metric in table.rows.items():
        n = max((c.n for c in by_metric.values() if c is not None), default=0)
        out = [method, str(n)]
        for m in table.metrics:
            out += _paired_cells(by_metric.get(m), m)
        lines.append("| " + " | ".join(out) + " |")
    lines += ["", f"Δ = method − {table.reference} over pairs (same dataset, scene, seed and setting; "
              "both finished); 95% BCa bootstrap interval of the mean over pairs (scipy); Wilcoxon p = the "
              "two-sided signed-rank test of the differences; W/L/T = "
              f"pairs where the method is better / worse / equal; d_z = the mean difference over its standard "
              "deviation (paired effect size), in brackets the pairs a two-sided paired t-test at 0.05 would need "
              "to detect it with 80% power (noncentral t): a 'no clear difference' with a small number there "
              "means too few seeds, with a large one no effect worth seeds. The verdict is 'better' only when "
              "the interval excludes zero, and none is drawn from fewer than 5 pairs."]
    lines += [f"Note: {n}" for n in table.notes]
    return "\n".join(lines) + "\n"


def paired_to_latex(table: PairedTable) -> str:
    cols = "lc" + "ccc" * len(table.metrics)
    lines = [r"% requires \usepackage{booktabs} and \usepackage{graphicx}", r"\begin{table}[t]", r"\centering",
             rf"\caption{{{_tex_escape(table.title)}}}", *FIT_OPEN, rf"\begin{{tabular}}{{{cols}}}", r"\toprule",
             " & & " + " & ".join(rf"\multicolumn{{3}}{{c}}{{{_tex_escape(PAIRED_LABELS.get(m, m))}}}"
                                  for m in table.metrics) + r" \\",
             "".join(rf"\cmidrule(lr){{{3 + 3 * i}-{5 + 3 * i}}}" for i in range(len(table.metrics))),
             "Method & Pairs & " + " & ".join(r"$\Delta$ [95\% CI] & W/L/T & $p$" for _ in table.metrics) + r" \\",
             r"\midrule"]
    for method, by_metric in table.rows.items():
        n = max((c.n for c in by_metric.values() if c is not None), default=0)
        out = [_tex_escape(method), str(n)]
        for m in table.metrics:
            cells = _paired_cells(by_metric.get(m), m)
            out += [tex_number(cells[0]) if cells[0] != MISSING else MISSING, cells[1],
                    cells[2].replace("<", "$<$")]
        lines.append(" & ".join(out) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", *FIT_CLOSE, r"\par\smallskip",
              rf"\parbox{{\linewidth}}{{\footnotesize $\Delta$ = method $-$ {_tex_escape(table.reference)} "
              r"over paired (scene, seed) runs; 95\% BCa bootstrap interval; $p$: Wilcoxon signed-rank"
              + "".join(rf" \\ Note: {_tex_escape(n)}" for n in table.notes) + "}", r"\end{table}"]
    return "\n".join(lines) + "\n"
