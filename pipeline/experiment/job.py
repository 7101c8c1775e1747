"""What a worker runs for one job: the episode (or the uncertainty experiment), with retries.

Workers never write to MLflow: they return a ``JobOutcome`` (the result and artifact bytes) that
the driver tracks. Their job folder holds the episode checkpoint (a killed job resumes from its last
finished round) and a log with one line per round. While a job runs, each finished round is also
handed to an optional ``report`` callable as a ``RoundMessage``; the executors carry it to the
driver, which prints it and logs it to the tracker.
"""

from __future__ import annotations

import json
import logging
import os
import time
import traceback
from pathlib import Path
from typing import Callable

import torch

from pipeline.active import run_episode
from pipeline.active.plan import EpisodePlan
from pipeline.active.uncertainty import run_uncertainty_experiment
from pipeline.data.fingerprint import scene_fingerprint
from pipeline.data.images import DataError
from pipeline.data.load import load_scene
from pipeline.data.scene import Scene
from pipeline.eval.images import colormap, png_bytes
from pipeline.experiment.resolution import MISSING_DATA
from pipeline.experiment.episode_settings import uncertainty_config
from pipeline.experiment.layout import BENCHMARK_RESULT, MODEL, JobFolder
from pipeline.experiment.result_document import result_document
from pipeline.experiment.outcome import FINISHED, JobOutcome, RoundMessage, StepProgress
from pipeline.data.synthetic import depth_truth
from pipeline.eval.camera_path import picked_path
from pipeline.eval.depth import depth_errors, sparse_depth_errors
from pipeline.data.colmap import observed_points
from pipeline.eval.model_uncertainty import final_model_uncertainty
from pipeline.fisher.variance import channel_variance_maps, variance_maps
from pipeline.splat import ply, render
from pipeline.splat.render import RenderOutput
from pipeline.cameras import Cameras
from pipeline.interchange.results import EpisodeResult
from pipeline.experiment.spec import Job


def set_threads(threads: int) -> None:
    """Torch (and BLAS/OpenMP) threads = the CPUs the job reserved: two jobs on two cores must
    not each start two threads."""
    torch.set_num_threads(threads)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(threads)


def job_logger(folder: Path) -> logging.Logger:
    """The job's logger (``gopre.job.<hash>``), writing its folder's ``log.txt`` wherever the job
    runs (a Ray worker, a SLURM task, the driver): a retry on another node appends to the same file.
    Failed attempts and warnings at WARNING, rounds at INFO."""
    logger = logging.getLogger(f"gopre.job.{folder.name}")
    path = str(JobFolder(folder).log_file.absolute())
    if not any(getattr(h, "baseFilename", None) == path for h in logger.handlers):
        for old in list(logger.handlers):  # the same hash in another folder (a test, a new output_dir)
            logger.removeHandler(old)
            old.close()
        handler = logging.FileHandler(path, delay=True)
        handler.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        logger.propagate = False
    return logger


def _log(folder: Path, line: str) -> None:
    job_logger(folder).log(logging.WARNING if line.startswith(("warning", "attempt")) else logging.INFO, line)


def close_job_log(folder: Path) -> None:
    """Close the job's log file (a driver running hundreds of jobs must not keep one open each)."""
    logger = logging.getLogger(f"gopre.job.{folder.name}")
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
        handler.close()


Report = Callable[[RoundMessage | StepProgress], None]  # rounds, and progress inside a round



def round_images(ep, rec, count: int) -> dict[str, bytes]:
    """PNGs of the model that made this round's pick: the render and the per-pixel predictive
    variance (sum over channels, S = 1 / (H_train + lambda) of the taken views) of ``count``
    fixed test views, and the picked view's ground truth as the series ``picked`` (``picked_2`` ...
    for the further picks of a batch round)."""
    g, bg = ep.trainer.rendered_gaussians, ep.background
    views = ep.curve_ids[:count]
    cams = ep.test.cameras[views]
    with torch.no_grad():
        renders = render(g, cams, bg).rgb.clamp(0, 1)
    picked = set(rec.selected)
    taken = ep.taken_cameras()[[k for k, i in enumerate(ep.taken) if i not in picked]]
    maps = variance_maps(g, taken, cams, bg)
    out = {}
    for i, view in enumerate(views):
        out[f"render_test_{view:04d}"] = png_bytes(renders[i])
        out[f"variance_test_{view:04d}"] = png_bytes(colormap(maps[i].float()))
    for k, view in enumerate(rec.selected):  # one image series (step = views); the id is in the records
        image = ep.acquired.image(view) if ep.acquired.is_acquired(view) else ep.pool.images[view]
        out["picked" if k == 0 else f"picked_{k + 1}"] = png_bytes(image)
    return out


def save_round_images(target: Path, images: dict[str, bytes]) -> None:
    """A round's PNGs in ``target`` (each written whole, then renamed: a kill never leaves half a file)."""
    target.mkdir(parents=True, exist_ok=True)
    for key, png in images.items():
        tmp = target / f".{key}.png.tmp"
        tmp.write_bytes(png)
        os.replace(tmp, target / f"{key}.png")


def uncertainty_row(truth: torch.Tensor, render: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] ground truth and render, [H, W] variance -> [H, 4W, 3]."""
    error = (render - truth).square().sum(-1)
    return torch.cat([truth, render.clamp(0, 1), colormap(error), colormap(variance)], 1)


def run_episode_job(job: Job, scene: Scene, folder: Path, report: Report | None = None) -> dict:
    cfg = job.episode
    started = time.time()  # the MLflow run of the job starts here, not at its first round
    plan = EpisodePlan.of(scene, cfg)  # made once: the episode, its messages and result.json share it
    rounds, curve_views = plan.evaluations, len(plan.curve_ids)
    pending_images: dict[int, dict[str, bytes]] = {}

    def on_selection(ep, rec):
        if job.execution.round_models:  # the model that made this pick, for gopre-view
            ply.save(ep.trainer.rendered_gaussians, JobFolder(folder).round_model(rec.round))
        count = job.execution.round_images
        if count > 0:
            pending_images[rec.round] = round_images(ep, rec, count)

    def on_round(rec):
        _log(folder, f"round {rec.round}: {rec.num_views} views, psnr {rec.test_psnr:.2f}, "
                     f"selected {rec.selected}, {rec.selection_seconds:.1f}s selection")
        images = pending_images.pop(rec.round, None)
        if images:  # kept in the job folder too: the tracker takes them from there when the message is lost
            save_round_images(JobFolder(folder).round_images_dir(rec.num_views), images)
        if report is not None:
            message = RoundMessage.of(rec, rounds)
            message.job_started, message.curve_views = started, curve_views
            message.images = images or {}
            report(message)
    def on_resume(done: int):  # a retried, interrupted or relaunched job continues where it stopped
        _log(folder, f"resuming from the checkpoint after {done} round(s)")
    said = [time.perf_counter()]

    def on_step(round_: int, done: int, total: int, phase: str = "training"):  # inside a round: every progress_seconds
        now = time.perf_counter()
        if now - said[0] < job.execution.progress_seconds or done == total:
            return
        said[0] = now
        step = StepProgress(round_, rounds, done, total, round(time.time() - started, 1), phase)
        _log(folder, step.text())
        if report is not None:
            report(step)
    result = run_episode(scene, cfg, JobFolder(folder).checkpoint_dir, on_round=on_round, on_selection=on_selection,
                         device=job.execution.device, on_resume=on_resume, on_step=on_step, plan=plan)
    if result.final.degraded:
        _log(folder, f"warning: final PSNR {result.final.curve_psnr_drop:.2f} dB below the last "
                     "round's on the same views (degraded)")
    views = scene.split(result.test_split)
    shown = result.test_ids[:job.renders]
    with torch.no_grad():
        background = scene.background.to(result.gaussians.means)
        rendered = render(result.gaussians, views.cameras[result.test_ids], background)
    every = rendered.rgb  # [T, H, W, 3]
    preds = every[:len(shown)]
    truth = views.images.stack(shown).to(preds)
    artifacts = {"selected_views.json": json.dumps({"initial": result.initial, "selected": result.selected,
                                                    "probes": result.probes}).encode(),
                 MODEL: ply.export_bytes(result.gaussians),  # the final model, INRIA 3DGS PLY
                 # the portable result (pipeline.interchange's schema): what gopre-report --results reads
                 BENCHMARK_RESULT: json.dumps(result_document(job, scene, plan, result, every), indent=1).encode()}
    for i, view in enumerate(shown):
        artifacts[f"renders/test_{view:04d}.png"] = png_bytes(torch.cat([truth[i], preds[i]], dim=1))
    # the final model's uncertainty against its error on the same views (MLflow artifacts, and the
    # pixel-level metrics of pipeline.eval.model_uncertainty in the final metrics)
    variance = measure_final_model(result, scene, rendered, len(shown), job.generate is not None)
    for view, truth_k, pred_k, var_k in zip(shown, truth, preds, variance if variance is not None else []):
        artifacts[f"uncertainty/test_{view:04d}.png"] = png_bytes(uncertainty_row(truth_k, pred_k, var_k.sum(-1)))
    return {"result": result.to_dict(), "artifacts": artifacts}


def taken_cameras(result: EpisodeResult, pool_cameras: Cameras) -> Cameras:
    """The cameras of an episode's initial and selected views, in order: pool ids index
    ``pool_cameras``, the ids after the pool's the captured views (``result.acquired_cameras``)."""
    ids = result.initial + result.selected
    n = len(pool_cameras)
    if all(i < n for i in ids):
        return pool_cameras[ids]
    if result.acquired_cameras is None:
        raise ValueError(f"views {[i for i in ids if i >= n]} are beyond the pool of {n}, and no captured "
                         "camera is kept")
    return Cameras.cat([result.acquired_cameras[[i - n]] if i >= n else pool_cameras[[i]] for i in ids])


def measure_final_model(result: EpisodeResult, scene: Scene, rendered: RenderOutput, shown: int,
                        generated: bool) -> torch.Tensor | None:
    """Set ``result.final``'s camera path, pixel-level uncertainty on the first ``shown`` test views
    and (the generated scene, whose true depth is known) their depth errors, from the final model
    ``result.gaussians`` and its render of every test view ``rendered`` ([T, H, W, ...], in
    ``result.test_ids`` order). Returns the shown views' per-channel variance [shown, H, W, 3]
    (None when none is shown). The episode job and ``fill_metrics`` (a sweep recorded before these
    metrics) both measure here."""
    views = scene.split(result.test_split)
    pool = scene.split(result.pool_split).cameras
    taken = taken_cameras(result, pool)
    result.final.path_length = picked_path(taken.centers, len(result.initial), pool.centers)
    if shown == 0:
        return None
    ids = result.test_ids[:shown]
    preds = rendered.rgb[:shown]
    truth = views.images.stack(ids).to(preds)
    background = scene.background.to(result.gaussians.means)
    variance = channel_variance_maps(result.gaussians, taken, views.cameras[ids], background).to(preds)
    record, curves = final_model_uncertainty(truth, preds, variance)
    result.final.uncertainty, result.final.uncertainty_curves = record.to_dict(), curves
    # the shown views are the first test views: their depth is rendered already
    result.final.depth = final_depth_errors(scene, views, ids, rendered.depth[:shown], rendered.alpha[:shown],
                                            variance.sum(-1), generated)
    return variance


def final_depth_errors(scene: Scene, views, ids: list[int], depth: torch.Tensor, alpha: torch.Tensor,
                       uncertainty: torch.Tensor, generated: bool) -> dict | None:
    """The rendered depth [S, H, W] of the test views ``ids`` against what the scene knows of its
    depth: the generated scene's ray-cast truth, a COLMAP scene's points each view observed; None
    for a scene without either (a Blender scene)."""
    if generated:
        errors = depth_errors(depth, alpha, depth_truth(views.cameras[ids]), uncertainty)
    elif scene.format == "colmap":
        model_root = scene.info.get("undistorted", scene.root)  # the model the cameras were read from
        points = observed_points(model_root, [views.names[i] for i in ids])
        cams = views.cameras[ids]
        errors = sparse_depth_errors(depth, alpha, cams.viewmats, cams.Ks, points, uncertainty)
    else:
        return None
    return None if errors is None else errors.to_dict()


def run_uncertainty_job(job: Job, scene: Scene, folder: Path, report: Report | None = None) -> dict:
    out = run_uncertainty_experiment(scene, job.episode, uncertainty_config(job))
    artifacts = {}
    for i, view in enumerate(out.map_ids):
        row = uncertainty_row(out.ground_truth[i], out.renders[i], out.variance_maps[i].sum(-1))
        artifacts[f"uncertainty/test_{view:04d}.png"] = png_bytes(row)
    result = out.to_dict()
    artifacts["sparsification.json"] = json.dumps(result).encode()
    _log(folder, f"uncertainty: AUSE {out.ause}")
    return {"result": result, "artifacts": artifacts}


def run_job(job: Job, scene: Scene | None = None, report: Report | None = None) -> dict:
    """Run one job once; ``scene`` comes from the object store, else it is read here;
    ``report`` hears every finished round (a ``RoundMessage``)."""
    ex = job.execution
    set_threads(ex.threads)
    folder = Path(ex.job_dir)
    folder.mkdir(parents=True, exist_ok=True)
    if scene is None:
        check_data_identity(job)
        scene = load_scene(job.scene_path, width=job.episode.fit.image_width, masks=job.masks)
    start = time.perf_counter()
    runner = run_uncertainty_job if job.kind == "uncertainty" else run_episode_job
    outcome = runner(job, scene, folder, report)
    outcome["seconds"] = round(time.perf_counter() - start, 2)
    return outcome


def check_data_identity(job: Job) -> None:
    """A node that reads the scene itself must hold the data the driver fingerprinted (the same
    bytes, wherever mounted): else one DataError naming the folder and both fingerprints (not retried)."""
    if job.generate is not None or not job.data_fingerprint or job.data_fingerprint == MISSING_DATA:
        return
    here = scene_fingerprint(job.scene_path, job.masks).short
    if here != job.data_fingerprint:
        raise DataError(f"{job.scene_path}: the scene's data on this node has fingerprint {here}, the driver's "
                        f"has {job.data_fingerprint}: another copy of the data (sync the folder on every node)")


def stop_request(err: BaseException) -> BaseException | None:
    """The exit or stop request behind an error, if any: a signal handler that raises SystemExit
    (submitit's requeue) or a stop (Ctrl-C) while a compiled kernel runs surfaces as a SystemError
    whose cause chain holds it. Such an error is not the job's: it must end the process."""
    seen, hops = err, 0
    while seen is not None and hops < 50:
        if not isinstance(seen, Exception):  # SystemExit, KeyboardInterrupt, SweepInterrupted
            return seen
        if type(seen).__name__ == "UncompletedJobError":  # submitit: out of requeues, the task must end
            return seen
        seen, hops = seen.__cause__ or seen.__context__, hops + 1
    return None


def transient(err: BaseException) -> bool:
    """Whether another attempt could end otherwise: input/output trouble (a file system or network
    hiccup), memory exhausted (the host's, or a device's: torch.OutOfMemoryError). Anything else (a
    bad option, a corrupted checkpoint, a wrong shape, a division by zero) fails the same way again,
    and is not retried. A lost worker process is the executor's to rerun (Ray, SLURM), not this."""
    missing = (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError)
    if isinstance(err, OSError):
        return not isinstance(err, missing)
    return isinstance(err, (MemoryError, torch.OutOfMemoryError))


def run_with_retries(job: Job, scene: Scene | None = None, report: Report | None = None) -> JobOutcome:
    """``run_job`` with up to ``execution.retries`` re-runs after a transient error (``transient``);
    the outcome says FINISHED, or FAILED with the traceback of each attempt. Never raises for an
    application error; an exit or stop request (``stop_request``) is raised, not retried."""
    try:
        return _attempts(job, scene, report)
    finally:
        close_job_log(Path(job.execution.job_dir))


def _attempts(job: Job, scene: Scene | None, report: Report | None) -> JobOutcome:
    attempts = 1 + max(0, int(job.execution.retries))
    errors = []
    for attempt in range(1, attempts + 1):
        try:
            outcome = run_job(job, scene, report)
            return JobOutcome(FINISHED, attempt, errors, outcome["result"], outcome["artifacts"],
                              outcome["seconds"])
        except Exception as err:
            stop = stop_request(err)
            if stop is not None:
                raise stop from None
            errors.append(traceback.format_exc())
            folder = Path(job.execution.job_dir)
            folder.mkdir(parents=True, exist_ok=True)
            again = transient(err) and attempt < attempts
            _log(folder, f"attempt {attempt}/{attempts} failed"
                         + ("" if again or attempt == attempts else " (deterministic: not retried)")
                         + f":\n{errors[-1]}")
            if not again:
                return JobOutcome.failed(attempt, errors)
    return JobOutcome.failed(attempts, errors)
