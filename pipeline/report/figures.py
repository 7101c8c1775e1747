"""Figures with matplotlib (Agg): PSNR vs views, sparsification curves, qualitative grids,
uncertainty maps next to error maps. Every function returns the path it wrote and the series it
drew (name -> (x, y)), so tests can check what is in a figure without looking at pixels."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from PIL import Image  # noqa: E402


def save_figure(fig, path: Path) -> None:
    """The figure as ``path`` (PNG, for the Markdown report) and beside it as vector PDF (for a
    paper), then closed. The PDF carries no creation date, so the same figure regenerated is the
    same file (a published report's figures change only when their content does)."""
    fig.savefig(path, dpi=120)
    fig.savefig(Path(path).with_suffix(".pdf"), metadata={"CreationDate": None})
    plt.close(fig)


def _curves(rounds: pd.DataFrame, path: Path, points, xlabel: str) -> dict[str, dict[str, tuple[list, list]]]:
    """One panel per scene and setting (sweep-axis values, e.g. the protocol), one line per method of
    ``points(rows of one method in one panel) -> (x, y)``; panels in rows of at most three."""
    setting = rounds["setting"].fillna("") if "setting" in rounds else pd.Series("", index=rounds.index)
    rounds = rounds.assign(panel=[f"{sc}, {st}" if st else sc for sc, st in zip(rounds["scene"], setting)])
    panels = list(dict.fromkeys(rounds["panel"]))
    cols = min(3, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    series: dict[str, dict[str, tuple[list, list]]] = {}
    methods = list(dict.fromkeys(rounds["method"]))
    colour = {m: f"C{i % 10}" for i, m in enumerate(methods)}  # one colour per method in every panel
    for ax, panel in zip(axes.flat, panels):
        part = rounds[rounds["panel"] == panel]
        series[panel] = {}
        for method in methods:
            data = part[part["method"] == method]
            if data.empty:
                continue
            x, y = points(data)
            series[panel][method] = (x, y)
            ax.plot(x, y, marker="o", ms=3, label=method, color=colour[method])
        ax.set_title(panel, fontsize=9)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR on the curve's test views (dB)", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    handles = [plt.Line2D([], [], color=colour[m], marker="o", ms=3, label=m) for m in methods]
    axes[0][0].legend(handles=handles, fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return series


def psnr_vs_views(rounds: pd.DataFrame, path: Path) -> dict[str, dict[str, tuple[list, list]]]:
    """PSNR against #views, one line per method (mean over seeds), one panel per scene and setting."""
    def points(data):
        curve = data.groupby("num_views")["psnr"].mean()
        return curve.index.tolist(), curve.tolist()
    return _curves(rounds, path, points, "number of views")


SELECTION_TIME_COLUMNS = ("selection_cpu_seconds", "selection_seconds")  # the first one recorded is used


def selection_time_column(rounds: pd.DataFrame) -> str | None:
    return next((c for c in SELECTION_TIME_COLUMNS if c in rounds and rounds[c].notna().any()), None)


def cumulative_selection_seconds(rounds: pd.DataFrame, column: str) -> pd.Series:
    """Per round row, the selection seconds its job spent before the round was evaluated: the sum of
    ``column`` over the job's earlier rounds (a round's selection comes after its evaluation)."""
    keys = [k for k in ("sweep", "config_hash") if k in rounds]
    ordered = rounds.sort_values([*keys, "num_views"], kind="stable")
    spent = pd.to_numeric(ordered[column], errors="coerce").fillna(0.0)
    before = spent.groupby([ordered[k] for k in keys]).cumsum() - spent
    return before.reindex(rounds.index)


def psnr_vs_selection_time(rounds: pd.DataFrame, path: Path) -> dict[str, dict[str, tuple[list, list]]] | None:
    """PSNR against the cumulative selection time (CPU seconds where recorded, else wall), one point
    per round: the mean over seeds of both; None when no selection time was recorded."""
    column = selection_time_column(rounds)
    if column is None:
        return None
    rounds = rounds.assign(spent=cumulative_selection_seconds(rounds, column))

    def points(data):
        curve = data.groupby("num_views")[["spent", "psnr"]].mean()
        return curve["spent"].tolist(), curve["psnr"].tolist()
    label = "cumulative selection CPU seconds" if column == "selection_cpu_seconds" else "cumulative selection seconds"
    return _curves(rounds, path, points, label)


def sparsification(curves: pd.DataFrame, ause: pd.DataFrame, path: Path) -> dict[str, tuple[list, list]]:
    """One panel per scene (the paper's Fig. 7): mean PSNR of the remaining views vs the fraction
    removed, the AUSE in the legend (means over the scene's jobs). Returns the curves, keyed by
    method for one scene and by "scene/method" for several."""
    scenes = list(dict.fromkeys(curves["scene"])) if "scene" in curves else [None]
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 3.6), squeeze=False)
    series = {}
    for ax, scene in zip(axes[0], scenes):
        part = curves if scene is None else curves[curves["scene"] == scene]
        scores = ause if scene is None or "scene" not in ause else ause[ause["scene"] == scene]
        mean_ause = scores.groupby("uncertainty_method")["ause"].mean()
        for name, data in part.groupby("uncertainty_method", sort=False):
            curve = data.groupby("fraction")["psnr"].mean()
            x, y = curve.index.tolist(), curve.tolist()
            series[name if len(scenes) == 1 else f"{scene}/{name}"] = (x, y)
            style = {"oracle": dict(color="black", ls="--"), "random": dict(color="gray", ls=":")}.get(name, {})
            label = name if name == "oracle" else f"{name} (AUSE {mean_ause.get(name, np.nan):.3f})"
            ax.plot(x, y, marker="o", ms=3, label=label, **style)
        seeds = sorted(set(part["seed"])) if "seed" in part else []
        if scene is not None:
            ax.set_title(f"{scene} ({len(seeds)} seed{'s' if len(seeds) != 1 else ''})", fontsize=9)
        ax.set_xlabel("fraction of test views removed (most uncertain first)")
        ax.set_ylabel("mean PSNR of the rest (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return series


PIXEL_ERRORS = {"mae": "MAE", "rmse": "RMSE", "dssim": "DSSIM"}


def pixel_sparsification(curves: pd.DataFrame, ause: dict[tuple[str, str, str], float], path: Path) -> dict:
    """Fig. 7 extended: one row per scene, one panel per error (MAE, RMSE, DSSIM). Per method the
    mean over its seeds of the kept pixels' error relative to all pixels' (``pixel_curves.relative``)
    against the fraction removed, most uncertain first; the oracle (mean over every job, black
    dashed) and a random ranking (1, grey dotted); the legend gives each method's mean AUSE (max-norm.,
    ``ause[(scene, method, error)]``). Returns the plotted means keyed "scene/error/method"."""
    scenes = list(dict.fromkeys(curves["scene"]))
    errors = [e for e in PIXEL_ERRORS if e in set(curves["error"])]
    fig, axes = plt.subplots(len(scenes), len(errors), figsize=(4.6 * len(errors), 3.4 * len(scenes)), squeeze=False)
    series = {}
    for row, scene in zip(axes, scenes):
        for ax, error in zip(row, errors):
            part = curves[(curves["scene"] == scene) & (curves["error"] == error)]
            for method, data in part.groupby("method", sort=False):
                mean = data.groupby("fraction")["by_uncertainty"].mean()
                series[f"{scene}/{error}/{method}"] = (mean.index.tolist(), mean.tolist())
                score = ause.get((scene, method, error), np.nan)
                ax.plot(mean.index, mean.values, marker="o", ms=2.5, lw=1.2, label=f"{method} (AUSE {score:.3f})")
            oracle = part.groupby("fraction")["oracle"].mean()
            ax.plot(oracle.index, oracle.values, color="black", ls="--", label="oracle")
            ax.axhline(1.0, color="gray", ls=":", label="random ranking")
            seeds = sorted(set(part["seed"]))
            ax.set_title(f"{scene}: {PIXEL_ERRORS[error]} ({len(seeds)} seed{'s' if len(seeds) != 1 else ''})", fontsize=9)
            ax.set_xlabel("fraction of pixels removed (most uncertain first)")
            ax.set_ylabel(f"{PIXEL_ERRORS[error]} of the rest / of all pixels")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6, loc="best", framealpha=0.6)
    fig.tight_layout()
    save_figure(fig, path)
    return series


def image_grid(images: dict[str, list[Path]], path: Path, title: str) -> dict[str, int]:
    """Rows = labels (methods), each row the images side by side; returns images per row."""
    rows = [(label, [np.asarray(Image.open(p).convert("RGB")) for p in files])
            for label, files in images.items() if files]
    if not rows:
        return {}
    cols = max(len(r) for _, r in rows)
    h, w = rows[0][1][0].shape[:2]
    fig, axes = plt.subplots(len(rows), cols, figsize=(cols * w / h * 2.2, len(rows) * 2.2), squeeze=False)
    for i, (label, imgs) in enumerate(rows):
        for j in range(cols):
            ax = axes[i][j]
            ax.axis("off")
            if j < len(imgs):
                ax.imshow(imgs[j])
        axes[i][0].set_title(label, loc="left", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
    return {label: len(imgs) for label, imgs in rows}


def qualitative_grid(renders: dict[str, list[Path]], path: Path) -> dict[str, list[str]]:
    """Rows = test views; the first column the ground truth (once per view), then one column per
    method. Each render artifact is [ground truth | render] side by side; views are matched across
    methods by file name. Returns the column and row labels."""
    views = sorted({p.name for files in renders.values() for p in files})
    if not views:
        return {}
    halves = {}  # (method, view) -> (truth, render)
    for method, files in renders.items():
        for p in files:
            img = np.asarray(Image.open(p).convert("RGB"))
            half = img.shape[1] // 2
            halves[(method, p.name)] = (img[:, :half], img[:, half:])
    methods = [m for m in renders if any((m, v) in halves for v in views)]
    h, w = next(iter(halves.values()))[0].shape[:2]
    cols = ["ground truth"] + methods
    fig, axes = plt.subplots(len(views), len(cols), figsize=(len(cols) * w / h * 2.0, len(views) * 2.0),
                             squeeze=False)
    for i, view in enumerate(views):
        truth = next(halves[(m, view)][0] for m in methods if (m, view) in halves)
        for j, label in enumerate(cols):
            ax = axes[i][j]
            ax.axis("off")
            image = truth if j == 0 else halves.get((label, view), (None, None))[1]
            if image is not None:
                ax.imshow(image)
            if i == 0:
                ax.set_title(label, fontsize=9)
        axes[i][0].text(-0.05, 0.5, Path(view).stem, transform=axes[i][0].transAxes, rotation=90,
                        va="center", ha="right", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return {"columns": cols, "rows": [Path(v).stem for v in views]}


def search_landscape(rounds: list, path: Path, title: str) -> dict[int, tuple[list, list]]:
    """One panel per searched round (``report.search.RoundLandscape``): every pose the search
    evaluated at (azimuth, elevation), coloured by its cost relative to the pool's best candidate
    (blue: better than any pool view); the star is the pose found (filled: captured, hollow: the
    pool pick stood). Returns round -> (relative costs, taken) drawn."""
    cols = min(4, len(rounds))
    rows = -(-len(rounds) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.3 * cols + 1.0, 3.0 * rows + 0.4), squeeze=False,
                             sharex=True, sharey=True, layout="constrained")  # one frame: the search moves
    rel = [r.relative_costs() * 100 for r in rounds]
    every = np.concatenate(rel)  # two slopes: the few points below the pool's best stay visible
    norm = matplotlib.colors.TwoSlopeNorm(vcenter=0.0, vmin=min(float(every.min()), -1e-3),
                                          vmax=max(float(np.percentile(every, 90)), 1e-3))
    drawn = {}
    for ax, r, values in zip(axes.flat, rounds, rel):
        points = ax.scatter(r.poses[:, 0], r.poses[:, 1], c=values, cmap="coolwarm", norm=norm,
                            s=14, edgecolors="none")
        ax.scatter([r.best[0]], [r.best[1]], marker="*", s=160, linewidths=1.2, edgecolors="black",
                   facecolors="black" if r.taken == "search" else "none")
        ax.set_title(f"round {r.round}: {'captured' if r.taken == 'search' else 'pool pick stood'}", fontsize=8)
        ax.set_xlabel("azimuth (deg)", fontsize=7)
        ax.set_ylabel("elevation (deg)", fontsize=7)
        ax.tick_params(labelsize=6)
        drawn[r.round] = (values.tolist(), r.taken)
    for ax in list(axes.flat)[len(rounds):]:
        ax.axis("off")
    bar = fig.colorbar(points, ax=axes, shrink=0.8)
    bar.set_label("cost vs the pool's best (%)", fontsize=8)
    fig.suptitle(title, fontsize=9)
    save_figure(fig, path)
    return drawn
