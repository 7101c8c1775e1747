"""What an episode returns (its rounds, its final metrics, the whole result) and what the
uncertainty experiment returns, as typed records
that travel as plain data (``to_dict`` / ``from_dict``) across Ray, into ``result.json`` and the
checkpoint, and back.

Metrics versions (``FinalMetrics.metrics_version``; a record without the field is version 1):
- 1: ``ssim`` was scikit-image's ``structural_similarity`` (the mean over the valid interior,
  5 px cropped at each border).
- 2: ``ssim`` is the zero-padded full-image mean that 3DGS and the papers report
  (``pipeline.eval.metrics.ssim_value``); scikit-image's is ``ssim_skimage``.
A version-1 record is read as version 2 with its SSIM under ``ssim_skimage`` and ``ssim`` missing
(None): the two conventions are never mixed under one name. ``gopre-eval --sweep DIR`` fills the
missing values from each finished job's final model (``ssim_source`` then says so); the per-round
curve SSIM of such a record stays missing (its round models are not kept).
Nothing a job selects or trains depends on the version, so the config hash does not include it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the tensors an episode hands back in-process, never part of the plain data
    from torch import Tensor

    from pipeline.cameras import Cameras
    from pipeline.splat import Gaussians

METRICS_VERSION = 2


def recorded(column: str | None = None, *, metric: str | None = None, tag: str | None = None,
             picks_only: bool = False) -> dict:
    """A field's metadata when it is a column of the sweep's records (``pipeline.experiment.record_columns``
    derives every column list from it): ``column`` its name there (default the field's); ``metric``: MLflow
    logs it as that metric (a round's at step = views trained on, the final model's at step 0) and the
    read-back takes it from there; ``tag``: as that MLflow tag; ``picks_only``: only a round that picked
    has it (the final row holds its mean over the picks). A new recorded quantity is one field."""
    return {"recorded": {"column": column, "metric": metric, "tag": tag, "picks_only": picks_only}}


def _check_keys(cls, data: dict) -> None:
    unknown = set(data) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"{cls.__name__}.from_dict: unknown keys {sorted(unknown)}")


@dataclass
class RoundRecord:
    """The state after training on ``num_views`` views, and the selection made from it."""

    round: int
    num_views: int = field(metadata=recorded())  # views trained on when evaluated (the curve's x)
    iteration: int = field(metadata=recorded())  # trainer step at evaluation
    test_psnr: float = field(metadata=recorded("psnr", metric="test_psnr"))  # on the curve's test views
    test_ssim: float | None = field(metadata=recorded("ssim", metric="test_ssim"))  # 3DGS's (None: version 1)
    num_gaussians: int = field(metadata=recorded(metric="num_gaussians"))
    train_seconds: float           # training since the previous record
    selected: list[int] = field(default_factory=list)  # pool ids picked after evaluation
    probes: list[int] = field(default_factory=list)    # probe ids drawn for this round
    scores: dict[int, float] = field(default_factory=dict)  # every candidate's score
    candidates: int = 0
    per_candidate_ms: float = field(default=0.0, metadata=recorded(metric="per_candidate_ms", picks_only=True))
    selection_seconds: float = field(default=0.0, metadata=recorded(metric="selection_seconds", picks_only=True))
    fisher_seconds: float = 0.0
    peak_rss_mb: float = field(default=0.0, metadata=recorded())
    # scikit-image's SSIM of the same views
    test_ssim_skimage: float | None = field(default=None, metadata=recorded("ssim_skimage", metric="test_ssim_skimage"))
    # the selection's CPU time (every thread of the process): unlike the wall time it does not grow
    # when other jobs share the cores, so per-round costs of concurrent jobs stay comparable
    selection_cpu_seconds: float | None = field(default=None, metadata=recorded(metric="selection_cpu_seconds",
                                                                                picks_only=True))
    # numba's one-time kernel compilation during this round's selection, taken out of
    # selection_seconds, selection_cpu_seconds and per_candidate_ms (a fresh machine's first rounds)
    compile_seconds: float = field(default=0.0, metadata=recorded())
    # world != dataset (views taken beyond the pool): the captured pose of each selected view (azimuth_deg,
    # elevation_deg, radius) and the search's account (score, best_start_score, best_pool_score,
    # evaluations, seconds, taken: "search" | "pool", evaluated: [[az, el, r, score], ...])
    poses: list[list[float]] | None = None
    search: dict | None = None

    @classmethod
    def from_dict(cls, data: dict) -> "RoundRecord":
        _check_keys(cls, data)
        if "test_ssim_skimage" not in data:  # version 1: its SSIM was scikit-image's
            data = {**data, "test_ssim_skimage": data["test_ssim"], "test_ssim": None}
        scores = {int(k): v for k, v in (data.get("scores") or {}).items()}  # JSON keys are strings
        return cls(**{**data, "scores": scores})


@dataclass
class FinalMetrics:
    """The final model's metrics on every test view of the protocol (means, then per view), its
    size and training, and the degradation flag (see ``pipeline.active.episode``)."""

    psnr: float = field(metadata=recorded(metric="final_psnr"))
    # 3DGS's SSIM (None: a version-1 record not filled)
    ssim: float | None = field(metadata=recorded(metric="final_ssim"))
    ssim_skimage: float | None = field(metadata=recorded(metric="final_ssim_skimage"))  # scikit-image's SSIM
    lpips: float | None = field(metadata=recorded(metric="final_lpips"))  # None when unavailable or disabled
    lpips_status: str = field(metadata=recorded(tag="lpips_status"))  # why LPIPS is (un)available
    test_views: int = field(metadata=recorded())
    per_view_psnr: list[float]
    per_view_ssim: list[float] | None
    per_view_ssim_skimage: list[float] | None
    num_gaussians: int = field(metadata=recorded())
    iterations: int = 0
    final_phase_iterations: int = 0
    schedule: dict = field(default_factory=dict)
    curve_psnr_drop: float = field(default=0.0, metadata=recorded(metric="curve_psnr_drop"))
    degraded: bool = field(default=False, metadata=recorded(tag="degraded"))
    nonfinite_steps: int = field(default=0, metadata=recorded(metric="nonfinite_steps"))
    # what ``ssim`` means (the module's text); the tag the read-back needs before any SSIM
    metrics_version: int = field(default=METRICS_VERSION, metadata=recorded(tag="metrics_version"))
    # or "model.ply": filled in afterwards from the final model
    ssim_source: str = field(default="episode", metadata=recorded())
    # the final model's pixel-level uncertainty on the job's rendered test views
    # (``pipeline.eval.model_uncertainty``; None: not measured, e.g. a job rendering no view)
    uncertainty: dict | None = None
    # the path through the picked cameras in pick order, over the pool's diameter (eval.camera_path)
    path_length: float | None = field(default=None, metadata=recorded(metric="path_length"))
    # depth error on the rendered test views where the truth is known (the generated scene; eval.depth)
    depth: dict | None = None
    # the pixel-level sparsification curves behind ``uncertainty``'s AUSE, unnormalised
    # (``pipeline.eval.model_uncertainty.sparsification_curves``; None: not measured)
    uncertainty_curves: dict | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "FinalMetrics":
        _check_keys(cls, data)
        if "metrics_version" not in data:  # version 1: its SSIM was scikit-image's
            data = {**data, "ssim_skimage": data.get("ssim"), "ssim": None,
                    "per_view_ssim_skimage": data.get("per_view_ssim"), "per_view_ssim": None,
                    "metrics_version": 1, "ssim_source": "missing (version 1)"}
        return cls(**data)


@dataclass
class EpisodeResult:
    scene: str
    strategy: str
    seed: int
    protocol: str
    initial: list[int]             # ids in the pool split
    selected: list[int]            # ids in pick order
    probes: list[list[int]]        # the probe ids drawn at each round
    pool_split: str                # the scene split the initial, selected and probe ids index
    test_split: str                # the scene split the test ids index
    test_ids: list[int]            # ids in the test split (final metrics)
    curve_ids: list[int]           # ids of the per-round curve's test views
    rounds: list[RoundRecord]
    final: FinalMetrics
    wall_seconds: float
    gaussians: Gaussians | None = None  # the final model (not part of ``to_dict``)
    # world != dataset: the poses of the captured views, in pick order (their ids follow the pool's)
    acquired_poses: list[list[float]] | None = None
    acquired_cameras: "Cameras | None" = None  # their cameras (not part of ``to_dict``)

    def to_dict(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)
               if f.name not in ("gaussians", "rounds", "final", "acquired_cameras")}
        if out["acquired_poses"] is None:  # a pool episode's result.json as it always was
            del out["acquired_poses"]
        out["rounds"] = [asdict(r) for r in self.rounds]
        out["final"] = self.final.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "EpisodeResult":
        _check_keys(cls, data)
        return cls(**{**data, "rounds": [RoundRecord.from_dict(r) for r in data["rounds"]],
                      "final": FinalMetrics.from_dict(data["final"])})


@dataclass
class UncertaintyResult:
    """The uncertainty experiment (``pipeline.active.uncertainty``): the views it trained on and
    ranked, each test view's PSNR and each method's uncertainty, the sparsification curves over
    ``fractions`` and their AUSE against the oracle; the maps' tensors stay out of ``to_dict``."""

    train_ids: list[int]
    test_ids: list[int]
    psnr: list[float]                        # per test view
    uncertainty: dict[str, list[float]]      # method -> per test view
    fractions: list[float]
    curves: dict[str, list[float]]           # method (and random, oracle) -> PSNR per fraction
    ause: dict[str, float]
    map_ids: list[int]                       # the test views with per-pixel maps
    variance_maps: Tensor | None = None      # [V, H, W, 3] predictive variance of the map views
    renders: Tensor | None = None            # [V, H, W, 3]
    ground_truth: Tensor | None = None       # [V, H, W, 3]

    TENSORS = ("variance_maps", "renders", "ground_truth")

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.TENSORS}

    @classmethod
    def from_dict(cls, data: dict) -> "UncertaintyResult":
        _check_keys(cls, data)
        return cls(**data)
