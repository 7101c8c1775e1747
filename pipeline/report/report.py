"""A sweep's records -> tables (.md/.tex), figures and the list of runs they were made from.

The layout follows what the sweep contains: without sweep axes, methods x (dataset x PSNR, SSIM,
LPIPS) (tables 1-4); with axes (probe count K, pool reduction), one row per setting with PSNR,
selection cost (tables 5-6); uncertainty jobs give the AUSE table and the sparsification figure.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.report import falls, figures, search
from pipeline.report.identity import check_rows, identity_markdown
from pipeline.report.pixel_curves import pixel_curves, relative
from pipeline.report.rows import finished
from pipeline.report.stats import default_reference, paired_comparisons, with_curve_area
from pipeline.report.tables import (UNCERTAINTY_METRICS, PairedTable, Table, build_table, paired_to_latex,
                                    paired_to_markdown, to_latex, to_markdown)

from pipeline.interchange.layout import RECORDS, SweepFolder  # the one spelling of the folder layout


def load_records(source: str | Path) -> pd.DataFrame:
    """Records from a sweep folder or a records.parquet path; a clear error when there are none."""
    path = Path(source)
    if path.is_dir():
        path = path / RECORDS
    if not path.exists():
        raise FileNotFoundError(f"{path}: no records file (run a sweep first, or pass its output folder)")
    frame = pd.read_parquet(path)
    if frame.empty or "kind" not in frame:
        raise ValueError(f"{path}: the records file has no rows")
    return in_config_order(with_metrics_version(frame))


def with_metrics_version(frame: pd.DataFrame) -> pd.DataFrame:
    """Rows recorded before metrics version 2 (no ``metrics_version``; see
    ``pipeline.interchange.results``) had scikit-image's SSIM under ``ssim``: it moves to
    ``ssim_skimage`` and their ``ssim`` (3DGS's) is missing, so one column never mixes the two."""
    frame = frame.copy()
    if "metrics_version" not in frame:
        frame["metrics_version"] = np.nan
    if "ssim_skimage" not in frame:
        frame["ssim_skimage"] = np.nan
    if "ssim" not in frame:
        return frame
    episode = frame["kind"].isin(["final", "round"]) & (frame.get("job_kind", "episode") == "episode")
    final_v1 = episode & (frame["kind"] == "final") & frame["metrics_version"].isna()
    # a round row carries no version: a version-2 one always has its scikit-image SSIM beside it
    legacy = final_v1 | (episode & (frame["kind"] == "round") & frame["ssim_skimage"].isna())
    ssim = pd.to_numeric(frame["ssim"], errors="coerce")
    frame["ssim_skimage"] = pd.to_numeric(frame["ssim_skimage"], errors="coerce").where(~legacy, ssim)
    frame["ssim"] = ssim.where(~legacy)
    frame["metrics_version"] = pd.to_numeric(frame["metrics_version"], errors="coerce").where(~final_v1, 1)
    return frame


def missing_ssim_note(final: pd.DataFrame) -> str | None:
    """The note for a table whose SSIM (3DGS's) is missing for some episodes."""
    if "ssim" not in final:
        return None
    missing = int(final["ssim"].isna().sum())
    if not missing:
        return None
    return (f"SSIM is 3DGS's (zero-padded windows, the mean over all pixels); {missing} of {len(final)} "
            "episodes were recorded before it (metrics version 1) and are left out of its cells; "
            "their scikit-image SSIM is in the records as ssim_skimage. `gopre-eval --sweep DIR` "
            "fills it in from each job's final model.")


EPISODE_KEY = ["scene", "method", "protocol", "setting", "seed"]
PAIRED_METRICS = ["psnr", "psnr_auc"]  # what paired comparisons compare


def combine_records(sources: list[str | Path], by_sweep: bool = False) -> pd.DataFrame:
    """The records of several sweeps as one frame (e.g. a study's rows and a preset's missing
    rows, reported as one table), in each sweep's config order, one sweep after the other.

    The same episode (scene, method, protocol, setting, seed) finished in two of them is an error
    naming both sweeps: which one to report is the user's choice (``--seeds`` or fewer sources).
    ``by_sweep``: each sweep is a setting of its own (its name, before the row's own setting), so
    the same episodes under two policies are compared instead (see ``sweep_settings``)."""
    frames, offset, named = [], 0, {}
    for source in sources:
        frame = load_records(source).copy()
        # where each row's job folders are (the figures' renders): the sweep folder
        frame["sweep_dir"] = str(Path(source) if Path(source).is_dir() else Path(source).parent)
        if by_sweep:
            for name in dict.fromkeys(frame["sweep"]):
                if name in named:
                    raise ValueError(f"{source} and {named[name]} are both sweep {name!r}: compared by "
                                     f"sweep, each needs its own name (run one with name=...)")
                named[name] = source
            frame["setting"] = sweep_settings(frame)
        if "job_index" in frame:
            frame["job_index"] = frame["job_index"] + offset
            offset = int(frame["job_index"].max()) + 1
        frames.append(frame)
    if len(frames) == 1:
        return frames[0]
    combined = pd.concat(frames, ignore_index=True)
    final = combined[(combined["kind"] == "final") & (combined["status"] == "FINISHED")]
    key = [k for k in EPISODE_KEY if k in final]
    twice = final[final.duplicated(key, keep=False)]
    if not twice.empty:
        first = twice.iloc[0]
        sweeps = sorted(set(twice[(twice[key] == first[key]).all(axis=1)]["sweep"]))
        where = ", ".join(f"{k}={first[k]}" for k in key)
        raise ValueError(f"the episode {where} finished in more than one of the sweeps {sweeps} "
                         f"({len(twice)} such rows in all); report them separately or drop one")
    return in_config_order(combined)


def sweep_settings(frame: pd.DataFrame) -> pd.Series:
    """Each row's setting prefixed by its sweep's name: 'name' or 'name, setting'."""
    own = frame["setting"].fillna("") if "setting" in frame else pd.Series("", index=frame.index)
    return pd.Series([f"{sweep}, {s}" if s else str(sweep) for sweep, s in zip(frame["sweep"], own)],
                     index=frame.index)


def in_config_order(frame: pd.DataFrame) -> pd.DataFrame:
    """Rows in the order the sweep config lists jobs (not the order they finished in)."""
    if "job_index" not in frame:
        return frame
    return frame.sort_values("job_index", kind="stable").reset_index(drop=True)


def degraded_jobs(final: pd.DataFrame) -> list[str]:
    """'method on scene (seed s): -x.xx dB' for every finished episode flagged ``degraded``."""
    if "degraded" not in final:
        return []
    bad = final[final["degraded"].fillna(False).astype(bool)]
    return [f"{r['method']} on {r['scene']} (seed {r['seed']}"
            f"{', ' + r['setting'] if r.get('setting') else ''}): final PSNR "
            f"{r['curve_psnr_drop']:.2f} dB below its last round" for _, r in bad.iterrows()]


def episode_tables(frame: pd.DataFrame, title: str, reference: str | None = None,
                   baseline_setting: str | None = None) -> list:
    """The main table; with sweep axes and several methods, a methods x datasets table per
    setting; the paired comparison against ``reference`` (default: gopre when it ran); with
    ``baseline_setting``, each method's other settings against that one (``setting_tables``)."""
    final = finished(frame, "final", "episode")
    if final.empty:
        return []
    final = with_curve_area(final, finished(frame, "round", "episode"))
    final = final.assign(setting=final["setting"].fillna(""))
    methods = list(dict.fromkeys(final["method"]))
    settings = list(dict.fromkeys(final["setting"]))
    tables: list = []
    if settings != [""]:
        rows = final.assign(row=[f"{m}, {s}" if len(methods) > 1 else s
                                 for m, s in zip(final["method"], final["setting"])])
        table = build_table(rows, title, "row", None,
                            ["psnr", "psnr_auc", "ssim", "per_candidate_ms", "selection_seconds"])
        tables.append(table)
        if len(methods) > 1:
            tables += [build_table(final[final["setting"] == s].rename(columns={"method": "Method"}),
                                   f"{title}, {s}: mean ± std over seeds", "Method", "dataset",
                                   ["psnr", "psnr_auc"], methods) for s in settings]
    else:
        table = build_table(final.rename(columns={"method": "Method"}), title, "Method", "dataset",
                            ["psnr", "psnr_auc", "ssim", "lpips"], methods)
        tables.append(table)
        tables += selection_time_table(final, title, methods)
        tables += uncertainty_table(final, title, methods)
    note = missing_ssim_note(final)
    if note:
        table.notes.append(note)
    bad = degraded_jobs(final)
    if bad:
        table.notes.append(f"{len(bad)} job(s) in these cells ended on a degraded model (final PSNR "
                           f"more than 3 dB below the last round's on the same views): "
                           + "; ".join(bad))
    tables += paired_tables(final, title, methods, settings, reference)
    if baseline_setting is not None:
        tables += setting_tables(final, title, methods, settings, baseline_setting)
    return tables


def setting_tables(final: pd.DataFrame, title: str, methods: list[str], settings: list[str],
                   baseline: str) -> list[PairedTable]:
    """One table: for every method, each other setting against ``baseline`` on final PSNR and the
    curve area, paired over (dataset, scene, seed): what a policy or option changes, method by
    method (rows 'method: setting')."""
    if baseline not in settings:
        raise ValueError(f"baseline setting {baseline!r} did not run; settings: {settings}")
    rows: dict[str, dict] = {}
    for method in methods:
        part = final[final["method"] == method]
        compared = comparisons(part.assign(method=part["setting"], setting=""), baseline, settings)
        rows.update({f"{method}: {setting}": by_metric for setting, by_metric in compared.items()})
    if not rows:
        return []
    return [PairedTable(f"{title}: each setting against {baseline}, method by method", baseline,
                        PAIRED_METRICS, rows)]


def uncertainty_table(final: pd.DataFrame, title: str, methods: list[str]) -> list[Table]:
    """The final model's pixel-level uncertainty per method (mean ± std over episodes), when the
    records have it (``pipeline.eval.model_uncertainty``)."""
    present = [m for m in UNCERTAINTY_METRICS if m in final and final[m].notna().any()]
    if not present:
        return []
    table = build_table(final.rename(columns={"method": "Method"}), f"{title}: pixel-level uncertainty of the final model",
                        "Method", None, present, methods)
    table.notes.append(
        "The map is each final model's Laplace predictive variance (S = 1 / (H_train + lambda) of the views its "
        "strategy took, per channel), on the job's rendered test views: a variance, so NLL and AUCE apply; it is the "
        "same recipe for every method, so these compare the calibration of the models the strategies built, not the "
        "strategies' own scores. AUSE: the area between the error of the pixels kept after removing the most "
        "uncertain fraction and the oracle's, for MAE (absolute error summed over channels), RMSE and DSSIM; "
        "max-norm. = both curves divided by their largest value over 100 fractions in [0, 1) (FisherRF, WarpRF, "
        "AaltoML's released code), start-norm. = divided by the error of all pixels, fractions in [0, 0.999], "
        "zero-error pixels dropped (3DGS-Uncertainty's). NLL: Gaussian, sigma floored at 0.03 (AaltoML). AUCE: "
        "the area under |coverage - (1 - alpha)| over alpha in 0.01 ... 0.99. Pearson and Spearman: summed variance "
        "against MAE. Lower is better for AUSE, NLL and AUCE, higher for the correlations. Depth: absolute "
        "relative error and RMSE of the rendered depth where the model is opaque (alpha >= 0.5), against the "
        "generated scene's ray-cast depth (every pixel its surface covers) or a COLMAP scene's structure-from-motion "
        "points (each test view's own observed points, at the pixel each falls in; RMSE in the model's units); "
        "Depth AUSE: the absolute relative depth error sparsified by the summed colour variance (no depth "
        "variance is computed), max-norm. (FisherRF's depth AUSE). A Blender scene has no depth to compare.")
    return [table]


def selection_time_table(final: pd.DataFrame, title: str, methods: list[str]) -> list[Table]:
    """Each method's selection cost beside its quality: the CPU seconds of one round's selection
    (mean over the episode's rounds, then over seeds), per dataset. CPU time, not wall time: jobs
    that share the cores do not inflate it. None when no method selected (random only)."""
    if "selection_cpu_seconds" not in final or final["selection_cpu_seconds"].isna().all():
        return []
    costs = ["selection_cpu_seconds"] + (["path_length"] if "path_length" in final and final["path_length"].notna().any()
                                         else [])
    table = build_table(final.rename(columns={"method": "Method"}),
                        f"{title}: selection CPU seconds per round" + (" and the camera path" if len(costs) > 1 else ""),
                        "Method", "dataset", costs, methods)
    table.notes.append("Lower is better. The CPU time of a round's selection (scoring every "
                       "candidate), mean over the episode's rounds, then mean ± std over seeds; "
                       "unlike wall time, other jobs on the same cores do not inflate it. Numba's "
                       "one-time kernel compilation (a fresh machine's first rounds) is taken out "
                       "of it and recorded apart (records column compile_seconds)."
                       + (" Camera path: the length of the path from the last initial view through the picks in "
                          "pick order, over the diameter of the pool's camera centres (a robot's travel; lower is "
                          "cheaper)." if len(costs) > 1 else ""))
    return [table]


def paired_tables(final: pd.DataFrame, title: str, methods: list[str], settings: list[str],
                  reference: str | None) -> list[PairedTable]:
    """Per setting, every method against ``reference`` on final PSNR and the curve area, over all
    scenes; with several scenes, then one table per scene (each scene's own verdicts: with five
    seeds a scene has the five pairs the rule asks for)."""
    reference = default_reference(methods, reference)
    if reference is None or len(methods) < 2:
        return []
    if reference not in methods:
        raise ValueError(f"reference method {reference!r} did not run; methods: {methods}")
    scenes = list(dict.fromkeys(final["scene"]))
    out = []
    for s in settings:
        part = final[final["setting"] == s]
        label = f", {s}" if s else ""
        out += _paired_table(part, f"{title}{label}", methods, reference)
        if len(scenes) > 1:
            for scene in scenes:
                out += _paired_table(part[part["scene"] == scene], f"{title}{label}, {scene} only",
                                     methods, reference)
    return out


def comparisons(part: pd.DataFrame, reference: str, order: list[str]) -> dict[str, dict]:
    """{method: {metric: PairedComparison}} of every method of ``part`` against ``reference`` on
    ``PAIRED_METRICS``, in ``order``; a metric the reference has no value of in ``part`` (e.g. a
    scene whose rounds were not recorded: no curve area) is left out, and {} when it did not run."""
    ours = part[part["method"] == reference]
    by_method: dict[str, dict] = {}
    for metric in PAIRED_METRICS:
        if metric not in ours or ours[metric].isna().all():
            continue
        for c in paired_comparisons(part, reference, metric, order):
            by_method.setdefault(c.method, {})[metric] = c
    return by_method


def _paired_table(part: pd.DataFrame, title: str, methods: list[str], reference: str) -> list[PairedTable]:
    """[every method against ``reference`` over ``part``'s pairs], or [] when it has none."""
    by_method = comparisons(part, reference, methods)
    if not by_method:
        return []
    return [PairedTable(f"{title}: paired differences against {reference}", reference, PAIRED_METRICS, by_method)]


def render_markdown(table) -> str:
    return paired_to_markdown(table) if isinstance(table, PairedTable) else to_markdown(table)


def render_latex(table) -> str:
    return paired_to_latex(table) if isinstance(table, PairedTable) else to_latex(table)


def ause_table(frame: pd.DataFrame, title: str) -> list[Table]:
    rows = finished(frame, "ause", "uncertainty")
    if rows.empty:
        return []
    rows = rows.rename(columns={"uncertainty_method": "Uncertainty"})
    return [build_table(rows, f"{title}: AUSE (PSNR, lower is better)", "Uncertainty", "dataset", ["ause"])]


def grid_images(sweep_dir: Path | None, final: pd.DataFrame, sub: str,
                scene: str | None = None, reference: str | None = None) -> dict[str, list[Path]]:
    """The first four ``sub`` images of each column of one scene's grid (default: the first
    scene), from its first seed: one column per method at the scene's first setting; when one
    method ran, or the rows come from several sweeps compared by sweep, one per setting of one
    method (the reference: gopre, else the first), and no grid of a scene only one of those sweeps
    ran. A row's images are under its own sweep's
    folder (``sweep_dir`` column of combined records), else under ``sweep_dir``."""
    if final.empty or (sweep_dir is None and "sweep_dir" not in final):
        return {}
    final = final.assign(setting=final["setting"].fillna("") if "setting" in final else "")
    compared = "sweep" in final and final["sweep"].nunique() > 1 and final["setting"].nunique() > 1
    part = final[final["scene"] == (scene if scene is not None else final["scene"].iloc[0])]
    part = part[part["seed"] == part["seed"].min()]
    if compared and part["sweep"].nunique() < 2:
        return {}  # a scene only one of the compared sweeps ran: its own report has its grid
    if part["method"].nunique() > 1 and not compared:
        part = part[part["setting"] == part["setting"].iloc[0]].drop_duplicates("method")
        labels = list(part["method"])
    else:
        one = default_reference(list(dict.fromkeys(part["method"])), reference) or part["method"].iloc[0]
        part = part[part["method"] == one].drop_duplicates("setting")
        labels = [f"{m} ({s})" if s else m for m, s in zip(part["method"], part["setting"])]
    own = part["sweep_dir"] if "sweep_dir" in part else [None] * len(part)
    out = {}
    for label, config_hash, folder in zip(labels, part["config_hash"], own):
        root = Path(folder) if isinstance(folder, str) else sweep_dir
        # a row from a result file (an outside method) has no job folder, hence no images
        if root is None or not isinstance(config_hash, str):
            out[label] = []
            continue
        images = SweepFolder(root).job(config_hash).artifacts / sub
        out[label] = sorted(images.glob("*.png"))[:4] if images.exists() else []
    return out


def pixel_ause(finals: pd.DataFrame) -> dict[tuple[str, str, str], float]:
    """(scene, method, error) -> the mean pixel-level AUSE (max-norm.) of the final rows."""
    out = {}
    for error in ("mae", "rmse", "dssim"):
        column = f"unc_ause_{error}_max"
        if column in finals:
            for (scene, method), value in finals.groupby(["scene", "method"])[column].mean().items():
                out[(scene, method, error)] = float(value)
    return out


def make_figures(frame: pd.DataFrame, sweep_dir: Path | None, out: Path,
                 reference: str | None = None, images: bool = True) -> dict[str, dict]:
    """The report's figures; ``images=False``: curves only, no figure made of the scene's images
    (the qualitative grids with their ground truth and renders, the uncertainty maps), for data
    whose license keeps its pictures out of a published report."""
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    made = {}
    rounds = finished(frame, "round", "episode")
    if not rounds.empty:
        made["psnr_vs_views.png"] = figures.psnr_vs_views(rounds, fig_dir / "psnr_vs_views.png")
        timed = figures.psnr_vs_selection_time(rounds, fig_dir / "psnr_vs_selection_time.png")
        if timed is not None:
            made["psnr_vs_selection_time.png"] = timed
    curves = finished(frame, "sparsification", "uncertainty")
    if not curves.empty:
        made["sparsification.png"] = figures.sparsification(
            curves, finished(frame, "ause", "uncertainty"), fig_dir / "sparsification.png")
    final = finished(frame, "final", "episode")
    pixel = pixel_curves(sweep_dir, final)
    if not pixel.empty:
        made["pixel_sparsification.png"] = figures.pixel_sparsification(
            relative(pixel), pixel_ause(final), fig_dir / "pixel_sparsification.png")
    if not images:
        return made
    for k, scene in enumerate(dict.fromkeys(final["scene"])):  # one grid per scene (paper Fig. 5)
        renders = grid_images(sweep_dir, final, "renders", scene, reference)
        if any(renders.values()):
            name = "qualitative.png" if k == 0 else f"qualitative_{scene}.png"
            made[name] = figures.qualitative_grid(renders, fig_dir / name)
    maps = grid_images(sweep_dir, finished(frame, "final", "uncertainty"), "uncertainty")
    if any(maps.values()):
        made["uncertainty_maps.png"] = figures.image_grid(
            {f"view {i}": [p] for files in maps.values() for i, p in enumerate(files)},
            fig_dir / "uncertainty_maps.png", "ground truth | render | squared error | predictive variance")
    return made


def search_section(frame: pd.DataFrame, sweep_dir: Path | None, out: Path, made: dict) -> list[str]:
    """Beyond the pool: how the searches went, what they cost, the landscapes they saw (also in
    ``search.md``); nothing when no method searched. Adds the landscape figures to ``made``."""
    if not search.searched_methods(frame):
        return []
    lines = ["## Beyond the pool: the pose searches", "",
             "A searched pose is captured only when its cost (the strategy's own score of the camera, "
             "a gain negated) is below the pool's best candidate's; otherwise the pool pick stands.",
             *search.world_notes(frame), "",
             search.search_table(frame), "Selection time per round (the search included):", "",
             search.selection_time_table(frame)]
    for k, (label, rounds) in enumerate(search.landscape_jobs(frame, sweep_dir).items() if sweep_dir else []):
        if rounds:
            name = f"search_landscape_{k}.png"
            made[name] = figures.search_landscape(rounds, out / "figures" / name, f"score landscape: {label}")
            lines.append(f"Landscape {k}: {label} (`figures/{name}`).")
    lines.append("")
    (out / "search.md").write_text("\n".join(lines) + "\n")
    return lines


def falls_section(frame: pd.DataFrame, out: Path) -> list[str]:
    """The curve's round-to-round falls per method (``falls.markdown``), every episode's in
    ``falls.csv``; nothing when no episode has rounds."""
    rows = falls.episode_falls(frame)
    if rows.empty:
        return []
    rows.to_csv(out / "falls.csv", index=False)
    return ["## Round-to-round falls of the curve", "", falls.falls_markdown(rows)]


def runs_table(frame: pd.DataFrame) -> pd.DataFrame:
    final = frame[frame["kind"] == "final"]
    cols = [c for c in ("sweep", "method", "dataset", "scene", "seed", "setting", "config_hash", "run_id",
                        "status", "psnr", "degraded", "attempts", "code_version", "data_fingerprint",
                        "plugin_version", "plugin_sha256") if c in final]
    return final[cols].sort_values(["method", "dataset", "scene", "seed"]).reset_index(drop=True)


def frame_to_markdown(frame: pd.DataFrame) -> str:
    def text(v):
        return "n/a" if v is None or (isinstance(v, float) and v != v) else (f"{v:.2f}" if isinstance(v, float) else str(v))
    lines = ["| " + " | ".join(frame.columns) + " |", "|" + "---|" * len(frame.columns)]
    lines += ["| " + " | ".join(text(v) for v in row) + " |" for row in frame.itertuples(index=False)]
    return "\n".join(lines)


def remove_stale_figures(fig_dir: Path, made: dict) -> list[str]:
    """Remove the PNG and PDF files in the report's own ``figures/`` that this report did not
    draw (an earlier report into the same folder drew them, from other records): a regenerated
    report holds only its own figures. Returns the names removed."""
    keep = {Path(name).stem for name in made}
    stale = sorted(p.name for p in fig_dir.glob("*") if p.suffix in (".png", ".pdf") and p.stem not in keep)
    for name in stale:
        (fig_dir / name).unlink()
    return stale


def make_report(source: str | Path, out: str | Path, frame: pd.DataFrame | None = None,
                reference: str | None = None, baseline_setting: str | None = None,
                images: bool = True, allow_mixed: bool = False) -> dict:
    """Write report.md, tables (.md, .tex), figures/, falls.csv and runs.csv into ``out``; returns
    a summary. ``reference``: the method the paired comparisons are against (default gopre when
    present); ``baseline_setting``: the setting each method's others are paired against;
    ``images=False``: no figure of the scenes' images (``make_figures``); ``allow_mixed``: report rows
    that average several code versions, plugins or data (``report.identity``) instead of refusing."""
    sweep_dir = Path(source) if Path(source).is_dir() else None
    frame = load_records(source) if frame is None else in_config_order(frame)
    check_rows(frame, allow_mixed)  # a row averages one method on one data, or the report says no
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sweeps = [str(name) for name in dict.fromkeys(frame["sweep"])]
    title = " + ".join(sweeps)  # several when sweeps are reported together (or compared by sweep)
    methods = list(dict.fromkeys(finished(frame, "final")["method"]))
    tables = (episode_tables(frame, title, reference, baseline_setting) + ause_table(frame, title)
              + search.twin_tables(frame, title, skip=default_reference(methods, reference)))
    markdown = "".join(render_markdown(t) + "\n" for t in tables)
    (out / "table.md").write_text(markdown)
    (out / "table.tex").write_text("\n".join(render_latex(t) for t in tables))
    made = make_figures(frame, sweep_dir, out, reference, images)
    runs = runs_table(frame)
    runs.to_csv(out / "runs.csv", index=False)
    failed = runs[runs["status"] != "FINISHED"]
    seeds = sorted(set(runs["seed"]))
    lines = [f"# Report: {title}", "", identity_markdown(frame), markdown, *falls_section(frame, out),
             *search_section(frame, sweep_dir, out, made), "## Figures", ""]
    if "psnr_vs_views.png" in made:
        lines += ["PSNR vs views averages the curve's test views (a fixed subset, "
                  "`splat.curve_test_views`); the tables' final PSNR uses every test view, so a curve's "
                  "last point differs from its table cell. Every figure is also in `figures/` as PDF.", ""]
    lines += [f"![{name}](figures/{name})" for name in made]
    if not images:
        lines += ["", "No figure of the scenes' images (ground truth, renders, uncertainty maps): "
                  "the report was made with `--no-images`."]
    stale = remove_stale_figures(out / "figures", made)
    lines += ["", "## Runs used", "",
              f"{len(runs)} jobs from sweep{'s' if len(sweeps) > 1 else ''} "
              f"{', '.join(f'`{name}`' for name in sweeps)}, seeds {seeds}; {len(failed)} failed (excluded). "
              "Every row: config hash and MLflow run id (runs.csv).", "",
              frame_to_markdown(runs)]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return {"out": str(out), "tables": markdown, "figures": {k: json.loads(json.dumps(v, default=str))
                                                             for k, v in made.items()},
            "runs": len(runs), "failed": len(failed), "removed_figures": stale}
