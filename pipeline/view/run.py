"""One episode as the viewer sees it: its job, scene, protocol views, rounds and models.

``load_run(source)`` reads a job folder ``outputs/<sweep>/jobs/<config hash>`` (its entry in the
sweep's ``jobs.json``, ``artifacts/result.json`` of a finished job or the checkpoint of one still
running, ``artifacts/model.ply`` and the per-round models ``rounds/round_NN.ply`` that
``job.round_models=true`` keeps), or an MLflow run id (its ``output_dir`` and ``config_hash`` tags
name that folder). ``EpisodeRun.round_state(r)`` is what the episode knew when it made the pick of
round ``r``: the views taken, the probes, every candidate's score, the pick, and the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import torch

from pipeline.active.config import EpisodeConfig
from pipeline.active.plan import EpisodePlan
from pipeline.cameras import Cameras
from pipeline.data.protocols import ProtocolViews
from pipeline.data.scene import Scene, Split
from pipeline.experiment.export import from_checkpoint
from pipeline.experiment.layout import JobFolder, SweepFolder
from pipeline.experiment.scene_lookup import scene_of
from pipeline.experiment.spec import Job
from pipeline.interchange.sweep_results import SweepResults
from pipeline.splat import Gaussians, ply



@dataclass
class RoundState:
    """The episode at the pick of one round (``index`` counts from 0)."""

    index: int
    taken: list[int]             # pool ids trained on when this round's pick was made
    probes: list[int]            # pool ids of this round's probe poses
    scores: dict[int, float]     # every candidate's score
    picked: list[int]            # the pool ids this round chose
    psnr: float                  # on the curve's test views, before the pick
    model: Gaussians
    model_is_final: bool         # True when this round's model was not kept (the final one stands in)


class CapturedImages:
    """The captured views' images (a tensor [A, H, W, 3]) behind the image store's interface."""

    def __init__(self, images: torch.Tensor):
        self.images = images

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int) -> torch.Tensor:
        return self.images[index]

    def stack(self, indices: list[int] | None = None) -> torch.Tensor:
        return self.images if indices is None else self.images[indices]


def captured_split(state: dict) -> Split | None:
    """The views an episode off the pool captured (a checkpoint's ``acquired`` state), as a split
    whose index a is the view with id ``pool size + a``; None when it captured none."""
    acquired = state.get("acquired") or {"poses": []}
    if not acquired["poses"]:
        return None
    cams = Cameras(acquired["viewmats"], acquired["Ks"], acquired["width"], acquired["height"])
    names = [f"captured at azimuth {p[0]:.1f}, elevation {p[1]:.1f}, radius {p[2]:.3g}" for p in acquired["poses"]]
    return Split(cams, CapturedImages(acquired["images"]), names)


@dataclass
class EpisodeRun:
    folder: Path
    job: Job
    cfg: EpisodeConfig
    scene: Scene
    plan: EpisodePlan            # the job's plan, made as the job made it
    initial: list[int]
    selected: list[int]
    rounds: list[dict]           # the selection rounds' records (the final evaluation excluded)
    final_model: Gaussians
    final_psnr: float | None     # None while the job runs
    round_models: dict[int, Path] = field(default_factory=dict)
    captured: Split | None = None  # views captured off the pool (world != dataset): ids after the pool's

    @property
    def views(self) -> ProtocolViews:
        return self.plan.views

    @property
    def pool(self) -> Split:
        return self.scene.split(self.views.pool_split)

    @property
    def test(self) -> Split:
        return self.scene.split(self.views.test_split)

    @property
    def first_captured(self) -> int:
        """The id of the first captured view (the pool split's size)."""
        return len(self.pool.cameras)

    def is_captured(self, view: int) -> bool:
        return view >= self.first_captured

    def cameras_of(self, ids: list[int]) -> Cameras:
        """Cameras of pool or captured view ids, in order."""
        if not any(self.is_captured(v) for v in ids):
            return self.pool.cameras[ids]
        return Cameras.cat([self.captured.cameras[[v - self.first_captured]] if self.is_captured(v)
                            else self.pool.cameras[[v]] for v in ids])

    def images_of(self, ids: list[int]) -> torch.Tensor:
        """[len(ids), H, W, 3] of pool or captured view ids, in order."""
        if not any(self.is_captured(v) for v in ids):
            return self.pool.images.stack(ids)
        return torch.stack([self.captured.images[v - self.first_captured] if self.is_captured(v)
                            else self.pool.images[v] for v in ids])

    @cached_property
    def pose_space(self):
        """The episode's pose space (off-pool runs), as the episode built it."""
        from pipeline.active.pose_selection import episode_pose_space
        return episode_pose_space(self.scene, self.views, self.cfg.protocol)

    @property
    def title(self) -> str:
        j = self.job
        return f"{j.method} on {j.scene} (seed {j.seed}, {j.protocol['kind']})"

    def model(self, index: int) -> tuple[Gaussians, bool]:
        """The model that made round ``index``'s pick, or the final one when it was not kept."""
        if index in self.round_models:
            return ply.load(self.round_models[index]), False
        return self.final_model, True

    def round_state(self, index: int) -> RoundState:
        if not 0 <= index < len(self.rounds):
            raise IndexError(f"round {index} outside 0..{len(self.rounds) - 1}")
        rec = self.rounds[index]
        before = sum(len(r["selected"]) for r in self.rounds[:index])
        model, is_final = self.model(index)
        return RoundState(index, self.initial + self.selected[:before], list(rec["probes"]),
                          {int(k): float(v) for k, v in rec["scores"].items()}, list(rec["selected"]),
                          float(rec["test_psnr"]), model, is_final)


def sweep_listing(folder: Path) -> str:
    """What to open in a sweep folder: one line per episode job (method / scene / seed / setting
    / config hash) and the command for one of them."""
    sweep = SweepFolder(folder)
    jobs = [j for j in sweep.read_jobs() if j.kind == "episode"]
    lines = [f"{folder} is a sweep folder; open one of its {len(jobs)} episode jobs:"]
    for j in jobs:
        setting = f", {j.setting}" if j.setting else ""
        path = sweep.job(j.config_hash).path
        done = "" if path.is_dir() else "  (not started)"
        lines.append(f"  {j.method} / {j.scene} / seed {j.seed}{setting}: {path}{done}")
    if jobs:
        lines.append(f"e.g. gopre-view {sweep.job(jobs[0].config_hash).path}")
    return "\n".join(lines)


def job_entry(folder: Path) -> Job:
    """The sweep's description of the job in ``folder`` (its ``jobs.json``, matched by hash)."""
    if SweepFolder(folder).jobs_file.exists():
        raise ValueError(sweep_listing(folder))
    listing = SweepFolder.of_job(folder).jobs_file
    if not listing.exists():
        raise ValueError(f"{folder}: no {listing} beside it (pass a job folder "
                         "outputs/<sweep>/jobs/<config hash>)")
    for job in SweepFolder(listing.parent).read_jobs():
        if job.config_hash == folder.name:
            if job.kind != "episode":
                raise ValueError(f"{folder}: a {job.kind!r} job, not an episode")
            return job
    raise ValueError(f"{folder}: no job with config hash {folder.name!r} in {listing}")


def load_folder(folder: Path, scene: str | None = None, data_root: str | None = None) -> EpisodeRun:
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such job folder")
    job = job_entry(folder)
    layout = JobFolder(folder)
    checkpoint = layout.checkpoint_file
    result = SweepResults(SweepFolder.of_job(folder).path).episode_data(folder.name)
    if result is not None:
        records, initial, selected = result["rounds"][:-1], result["initial"], result["selected"]
        final_psnr = float(result["final"]["psnr"])
        saved = layout.model_file  # absent in runs older than the exporter
        if saved.exists():
            model = ply.load(saved)
        elif checkpoint.exists():
            model = from_checkpoint(checkpoint)
        else:
            raise ValueError(f"{folder}: no final model (neither artifacts/model.ply nor checkpoint/episode.pt)")
    elif checkpoint.exists():  # still running: the rounds so far, the model of the last one
        result, state = None, torch.load(checkpoint, weights_only=False, map_location="cpu")
        done = bool(state.get("done"))
        records = state["records"][:-1] if done else state["records"]
        picked = [i for r in records for i in r["selected"]]
        initial, selected = state["taken"][:len(state["taken"]) - len(picked)], picked
        final_psnr, model = None, from_checkpoint(checkpoint)
    else:
        raise ValueError(f"{folder}: neither artifacts/result.json nor checkpoint/episode.pt: "
                         "the job has not finished a round")
    captured = None
    if job.world is not None:  # the captured views live in the checkpoint
        if not checkpoint.exists():
            raise ValueError(f"{folder}: an episode off the pool needs its checkpoint (the captured views)")
        captured = captured_split(torch.load(checkpoint, weights_only=False, map_location="cpu"))
    cfg = job.episode
    scene = scene_of(job, result, scene, data_root)
    plan = EpisodePlan.of(scene, cfg)
    kept = {i: layout.round_model(i) for i in range(len(records))}
    return EpisodeRun(folder, job, cfg, scene, plan, list(initial), list(selected), list(records),
                      model, final_psnr, {i: p for i, p in kept.items() if p.exists()}, captured)


def folder_of_mlflow_run(uri: str, run_id: str) -> Path:
    from mlflow import MlflowClient  # the tracking edge
    try:
        tags = MlflowClient(tracking_uri=uri).get_run(run_id).data.tags
    except Exception as err:
        raise ValueError(f"MLflow run {run_id} at {uri}: {type(err).__name__}: {err}") from None
    if "output_dir" not in tags or "config_hash" not in tags:
        raise ValueError(f"MLflow run {run_id} at {uri}: not a job run (no output_dir/config_hash tags)")
    return SweepFolder(Path(tags["output_dir"])).job(tags["config_hash"]).path


def load_run(source: str, mlflow_uri: str | None = None, scene: str | None = None,
             data_root: str | None = None) -> EpisodeRun:
    """A job folder, or an MLflow run id with ``mlflow_uri``; ValueError names what is missing.
    ``scene`` / ``data_root``: where the scene is when not where the job ran."""
    folder = folder_of_mlflow_run(mlflow_uri, source) if mlflow_uri else Path(source)
    return load_folder(folder, scene, data_root)
