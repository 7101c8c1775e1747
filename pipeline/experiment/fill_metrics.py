"""Fill in what a finished sweep's records lack, from each job's final model: the 3DGS SSIM of
episodes recorded before metrics version 2 (``pipeline.interchange.results``), and the final model's
pixel-level uncertainty, camera path and (generated scene) depth errors of episodes recorded before
those were measured (``fill_uncertainty``).

For each finished episode job whose ``artifacts/result.json`` is version 1, the final model
``artifacts/model.ply`` is rendered on the episode's own test views, and:
- its per-view PSNR must equal the recorded one (to ``PSNR_TOLERANCE_DB``), and its scikit-image
  SSIM the recorded SSIM (to ``SSIM_TOLERANCE``), else the job is refused and left as it was:
  the model is not the one that was scored;
- then ``ssim`` (3DGS's) and its per-view values are written, scikit-image's stay under
  ``ssim_skimage``, ``metrics_version`` becomes 2 and ``ssim_source`` "model.ply", in
  ``result.json`` (atomically) and in the job's rows of ``records.parquet``. The per-round curve
  SSIM stays missing (round models are not kept). MLflow runs are not touched: their
  ``final_ssim`` keeps its version-1 meaning, which ``records_from_mlflow`` reads as such.
Nothing is trained or selected; a second run finds nothing to do.

``fill_uncertainty``: for each finished episode whose result lacks today's final-model measures (no
``final.uncertainty`` or its sparsification curves ``final.uncertainty_curves``, or no depth errors
with their AUSE on a scene that knows its depth), the final
model is rendered on all its test views, must reproduce the recorded per-view PSNR (the same check),
and ``job.measure_final_model`` (the code a job runs today) measures it on the job's first ``renders``
test views with the posterior of the views it took (``selected_views``' initial + selected, as the
result lists them). ``result.json`` and the final row of ``records.parquet`` get the ``unc_*``,
``path_length`` and ``depth_*`` values (the curves go to ``result.json`` only); a value recorded
before that the code measures differently now (beyond 1e-6, relative) refuses the job instead of
being overwritten; MLflow runs are not touched. An episode of a capture world
(views taken at poses outside the pool: their cameras are not kept) is refused.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import torch

from pipeline.interchange.results import METRICS_VERSION, EpisodeResult
from pipeline.eval.metrics import evaluate_views
from pipeline.experiment.layout import JobFolder, SweepFolder
from pipeline.interchange.sweep_results import SweepResults
from pipeline.experiment.records import RecordsFile, depth_columns, uncertainty_columns
from pipeline.experiment.scene_lookup import scene_of
from pipeline.splat import ply, render
from pipeline.experiment.spec import Job

PSNR_TOLERANCE_DB = 1e-6
SSIM_TOLERANCE = 1e-9


@dataclass
class FillReport:
    filled: list[str] = field(default_factory=list)      # config hashes
    current: list[str] = field(default_factory=list)     # already version 2
    refused: dict[str, str] = field(default_factory=dict)  # config hash -> why

    def summary(self) -> str:
        out = f"{len(self.filled)} filled, {len(self.current)} already current, {len(self.refused)} refused"
        return out + "".join(f"\n  refused {h}: {why}" for h, why in self.refused.items())


def read_jobs(sweep: SweepFolder) -> list[Job]:
    if not sweep.jobs_file.exists():
        raise ValueError(f"{sweep.path}: no jobs.json (not a sweep folder)")
    return sweep.read_jobs()


Fill = Callable[[Job, JobFolder, EpisodeResult, "str | None", dict], EpisodeResult]
Rows = Callable[[pd.DataFrame, str, EpisodeResult], list[dict]]


def fill_each(folder: str | Path, data_root: str | None, current: Callable[[Job, EpisodeResult], bool],
              fill: Fill, rows: Rows, said: Callable[[Job, EpisodeResult], str],
              progress: Callable[[str], None]) -> FillReport:
    """Every finished episode of the sweep that is not ``current``: ``fill`` computes what it lacks
    (a ValueError refuses it, leaving it as it was), then its result.json and its records rows
    (``rows``) are written and ``said`` is printed."""
    sweep = SweepFolder(Path(folder))
    results = SweepResults(sweep.path)
    records = RecordsFile(sweep.path)
    report = FillReport()
    scenes: dict = {}  # (scene, width) -> Scene: a sweep's jobs share a few scenes
    for job in read_jobs(sweep):
        layout = sweep.job(job.config_hash)
        episode = results.episode(job.config_hash) if job.kind == "episode" else None
        if episode is None:
            continue
        if current(job, episode):
            report.current.append(job.config_hash)
            continue
        try:
            filled = fill(job, layout, episode, data_root, scenes)
        except ValueError as err:
            report.refused[job.config_hash] = str(err)
            continue
        write_result(layout, filled)
        if not records.frame.empty:
            records.add(rows(records.frame, job.config_hash, filled))
        report.filled.append(job.config_hash)
        progress(said(job, filled))
    return report


def fill_ssim(folder: str | Path, data_root: str | None = None,
              progress: Callable[[str], None] = lambda line: None) -> FillReport:
    """The 3DGS SSIM of every episode recorded before metrics version 2; see the module docstring."""
    return fill_each(folder, data_root, lambda job, ep: ep.final.metrics_version >= METRICS_VERSION,
                     filled_episode, filled_rows,
                     lambda job, ep: (f"{job.method} on {job.scene} (seed {job.seed}): SSIM {ep.final.ssim:.4f} "
                                      f"(scikit-image {ep.final.ssim_skimage:.4f})"), progress)


def fill_uncertainty(folder: str | Path, data_root: str | None = None,
                     progress: Callable[[str], None] = lambda line: None) -> FillReport:
    """Measure the final model's uncertainty (and camera path, and depth where known) of every
    finished episode recorded without it; see the module docstring."""
    def said(job: Job, ep: EpisodeResult) -> str:
        unc = ep.final.uncertainty or {}
        return (f"{job.method} on {job.scene} (seed {job.seed}): AUSE MAE {unc['ause_mae_max']:.3f} (max-norm.), "
                f"NLL {unc['nll']:.2f}, AUCE {unc['auce']:.3f}")
    return fill_each(folder, data_root, lambda job, ep: measured_already(job, ep) or job.renders == 0,
                     measured_episode, measured_rows, said, progress)


def measured_already(job: Job, episode: EpisodeResult) -> bool:
    """Whether the episode has today's final-model measures: the uncertainty, and the depth errors
    with their AUSE where the scene knows its depth (generated, COLMAP)."""
    final = episode.final
    if final.uncertainty is None or final.uncertainty_curves is None:
        return False
    knows_depth = job.generate is not None or job.format == "colmap"
    return not knows_depth or (final.depth is not None and "ause_abs_rel" in final.depth)


def measured_episode(job: Job, layout: JobFolder, episode: EpisodeResult, data_root: str | None,
                     scenes: dict) -> EpisodeResult:
    """The episode with ``final``'s uncertainty, camera path and depth measured from its model
    (ValueError when the model does not reproduce the recorded PSNR)."""
    from pipeline.experiment.job import measure_final_model  # the worker's code (torch, the kernels)
    if not layout.model_file.exists():
        raise ValueError(f"no {layout.model_file}")
    if episode.acquired_poses:
        raise ValueError(f"{layout.result_file}: views taken in a capture world (their cameras are not kept)")
    if job.masks:
        raise ValueError(f"{layout.result_file}: a masked episode (its PSNR is over the masks; not checked here)")
    scene, model, _ = scored_model(job, layout, episode, data_root, scenes, ssim=False)
    test, ids = scene.split(episode.test_split), episode.test_ids
    with torch.no_grad():
        rendered = render(model, test.cameras[ids], scene.background.to(model.means))
    out = replace(episode, final=replace(episode.final), gaussians=model)
    measure_final_model(out, scene, rendered, min(job.renders, len(ids)), job.generate is not None)
    for name, before, now in (("uncertainty", episode.final.uncertainty, out.final.uncertainty),
                              ("depth", episode.final.depth, out.final.depth)):
        moved = changed_values(before, now)
        if moved:  # measured before by other code: refuse rather than overwrite silently
            raise ValueError(f"{layout.result_file}: the {name} measured again differs from the recorded one "
                             f"({moved}): not filled")
    return replace(out, gaussians=None)


def changed_values(before: dict | None, now: dict | None, tolerance: float = 1e-6) -> str:
    """'key recorded -> now, ...' for the numbers ``before`` had that ``now`` changes (relative
    ``tolerance``); '' when none did or nothing was recorded."""
    if not before or not now:
        return ""
    moved = []
    for key, old in before.items():
        if not isinstance(old, (int, float)):
            continue
        new = now.get(key)
        if isinstance(new, (int, float)) and (abs(new - old) <= tolerance * max(1.0, abs(old))
                                              or (old != old and new != new)):  # NaN recorded, NaN again
            continue
        moved.append(f"{key} {old:.6g} -> {new}")
    return ", ".join(moved[:3])


def scored_model(job: Job, layout: JobFolder, episode: EpisodeResult, data_root: str | None, scenes: dict,
                 ssim: bool):
    """(the scene, the final model, its metrics on the episode's test views) once the model
    reproduces the recorded per-view PSNR (to ``PSNR_TOLERANCE_DB``), else ValueError: not the
    model that was scored. ``scenes`` caches the scenes read so far."""
    if not layout.model_file.exists():
        raise ValueError(f"no {layout.model_file}")
    key = (job.scene_path, episode.scene, job.episode.fit.image_width)
    if key not in scenes:
        scenes[key] = scene_of(job, {"scene": episode.scene}, None, data_root)
    scene = scenes[key]
    test, ids = scene.split(episode.test_split), episode.test_ids
    model = ply.load(layout.model_file)
    m = evaluate_views(model, test.cameras[ids], test.images.stack(ids), scene.background.to(model.means), ssim=ssim)
    psnr_gap = float(np.max(np.abs(np.subtract(m.psnr, episode.final.per_view_psnr))))
    if not psnr_gap <= PSNR_TOLERANCE_DB:
        raise ValueError(f"{layout.model_file} does not reproduce the recorded PSNR (largest per-view "
                         f"gap {psnr_gap:.3g} dB): not the model that was scored")
    return scene, model, m


def measured_rows(frame: pd.DataFrame, config_hash: str, episode: EpisodeResult) -> list[dict]:
    """The job's records rows, its final row with the measured columns."""
    rows = frame[frame["config_hash"] == config_hash].to_dict("records")
    final = episode.final
    for row in rows:
        if row["kind"] == "final":
            row.update(path_length=final.path_length, **uncertainty_columns(final.uncertainty),
                       **depth_columns(final.depth))
    return rows


def filled_episode(job: Job, layout: JobFolder, episode: EpisodeResult, data_root: str | None,
                   scenes: dict | None = None) -> EpisodeResult:
    """The episode with its final 3DGS SSIM computed from ``artifacts/model.ply``; ValueError when
    the model does not reproduce the recorded PSNR and scikit-image SSIM. ``scenes`` caches the
    scenes read so far."""
    _, _, m = scored_model(job, layout, episode, data_root, {} if scenes is None else scenes, ssim=True)
    final = episode.final
    if final.per_view_ssim_skimage is not None:
        ssim_gap = float(np.max(np.abs(np.subtract(m.ssim_skimage, final.per_view_ssim_skimage))))
        if not ssim_gap <= SSIM_TOLERANCE:
            raise ValueError(f"{layout.model_file} does not reproduce the recorded scikit-image SSIM "
                             f"(largest per-view gap {ssim_gap:.3g})")
    new = replace(final, ssim=float(np.mean(m.ssim)), per_view_ssim=list(m.ssim),
                  metrics_version=METRICS_VERSION, ssim_source="model.ply")
    return replace(episode, final=new)


def write_result(layout: JobFolder, episode: EpisodeResult) -> None:
    tmp = layout.result_file.with_suffix(".tmp")
    tmp.write_text(json.dumps(episode.to_dict(), default=str))
    os.replace(tmp, layout.result_file)


def filled_rows(frame: pd.DataFrame, config_hash: str, episode: EpisodeResult) -> list[dict]:
    """The job's records rows with the version-2 SSIM columns (final: both SSIMs; rounds: the old
    value moved to ``ssim_skimage``, ``ssim`` missing)."""
    rows = frame[frame["config_hash"] == config_hash].to_dict("records")
    final = episode.final
    for row in rows:
        if row["kind"] == "final":
            row.update(ssim=final.ssim, ssim_skimage=final.ssim_skimage,
                       metrics_version=final.metrics_version, ssim_source=final.ssim_source)
        elif row["kind"] == "round" and not _present(row.get("ssim_skimage")):
            row.update(ssim_skimage=row.get("ssim"), ssim=None)
    return rows


def _present(value) -> bool:
    return value is not None and value == value
