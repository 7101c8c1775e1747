"""One job of a sweep, typed: what it computes (hashed), where and how it runs (not hashed).

``expand_jobs`` builds each job's plain form (the dict the config hash and ``jobs.json`` have
always been made of, so finished sweeps still resume) and returns ``Job`` records; across Ray a job
travels as ``to_dict()`` and comes back with ``from_dict``. ``protocol``, ``splat``, ``options``,
``generate`` and ``uncertainty`` stay mappings: they are the config's sections, turned into the
core's dataclasses by ``pipeline.experiment.episode_settings`` (``episode_config``,
``uncertainty_config``). ``pipeline.experiment.resolution`` makes the jobs of a sweep.

A job's identity is ``config_hash``: the hash of what it computes (no paths, no execution settings).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import MISSING, asdict, dataclass, field, fields
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pipeline.active.config import EpisodeConfig


# Part of every job's hash: bumped when a fix changes what the same config computes, so a sweep
# never resumes or reuses results of the code before it. "fidelity-1": the paper-fidelity fixes (scene extent,
# tau -> 0, ActiveNeRF port, prune switch, kNN scales, probes incl. the initial views).
RESULTS_REVISION = "fidelity-1"
NOT_HASHED = ("execution", "scene_path", "sweep", "index", "code_version", "config_hash")


@dataclass(frozen=True)
class Execution:
    """How and where a job runs; none of it is in the hash."""

    threads: int
    device: str
    retries: int
    round_images: int
    round_models: bool
    job_dir: str
    progress_seconds: float = 30.0  # a training-progress line inside a round at most this often


@dataclass
class Job:
    sweep: str
    results_revision: str
    kind: str                        # episode | uncertainty
    dataset: str                     # the dataset key in the config
    format: str                      # blender | colmap
    scene: str
    scene_path: str
    generate: dict | None            # the generated scene's options (None: a dataset on disk)
    method: str                      # the method key (a config name: gopre, gopre_tau0, ...)
    strategy: str                    # the acquisition strategy it runs
    options: dict                    # the strategy's options
    protocol: dict                   # the protocol section (kind, budget, probes, ...)
    splat: dict                      # the splat section (preset and its overrides)
    seed: int
    renders: int
    uncertainty: dict | None         # the uncertainty section of an uncertainty job
    axes: dict = field(default_factory=dict)  # this job's sweep-axis values
    setting: str = ""                # the axes as "key=value, ..."
    config_hash: str = ""
    execution: Execution | None = None
    index: int | None = None         # the config's order (tables keep it)
    code_version: str | None = None
    world: dict | None = None        # the capture simulator off the pool (None: the dataset's pool)
    # a strategy from outside the package: its PluginIdentity as a dict (reference, distribution,
    # version, source_sha256), part of the hash so a changed plugin is re-run; None for a built-in
    plugin: dict | None = None
    masks: bool = False              # the dataset's masks: training and evaluation ignore masked-out pixels
    # the scene's data identity (``pipeline.data.fingerprint``): part of the hash, so changed data (an
    # edited generator, for the generated scene) is re-run; "" for a job made before data identity
    # (its hash is the old one)
    data_fingerprint: str = ""

    def to_dict(self) -> dict:
        """The plain form, key for key as ``jobs.json`` has always held it (``world`` only when a
        job captures off the pool, so a pool job's hash is what it always was)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["execution"] = asdict(self.execution) if self.execution is not None else None
        for optional in ("world", "plugin", "masks", "data_fingerprint"):  # absent when unused: older jobs hash as before
            if out[optional] in (None, False, ""):
                del out[optional]
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Job":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"Job.from_dict: unknown keys {sorted(unknown)}")
        missing = sorted(f.name for f in fields(cls) if f.name not in data
                         and f.default is MISSING and f.default_factory is MISSING)
        if missing:
            raise ValueError(f"Job.from_dict: missing keys {missing}")
        execution = data.get("execution")
        return cls(**{**data, "execution": Execution(**execution) if execution else None})

    @property
    def episode(self) -> "EpisodeConfig":
        """The core's episode config of this job (``episode_settings.episode_config``), resolved once and kept:
        every reader (the worker, the plan, scene loading, the viewer, result files) shares it."""
        cached = self.__dict__.get("_episode")
        if cached is None:
            from pipeline.experiment.episode_settings import episode_config  # torch: only when resolved
            cached = self.__dict__["_episode"] = episode_config(self)
        return cached

    @property
    def data_identity(self) -> str | None:
        """What the records, tags and result files name as the job's data: the fingerprint, or for a
        generated job made before the generator entered it the digest of its options (what its records
        name), or None (a job made before data identity)."""
        if self.data_fingerprint:
            return self.data_fingerprint
        if self.generate is not None:
            from pipeline.data.fingerprint import options_identity
            return options_identity(self.generate)
        return None

    @property
    def label(self) -> str:
        """'method on scene (seed s, setting)', as the driver's lines and the reports name a job."""
        setting = f", {self.setting}" if self.setting else ""
        return f"{self.method} on {self.scene} (seed {self.seed}{setting})"


def config_hash(job: dict | Job) -> str:
    """Stable hash of what a job computes (no paths, no execution settings), of its plain form."""
    plain = job.to_dict() if isinstance(job, Job) else job
    core = {k: v for k, v in plain.items() if k not in NOT_HASHED}
    return hashlib.sha256(json.dumps(core, sort_keys=True, default=str).encode()).hexdigest()[:16]


def without_data_identity(job: Job) -> str:
    """The hash the same job had before data identity (no fingerprint in it): what a sweep folder
    launched before it recorded."""
    plain = job.to_dict()
    plain.pop("data_fingerprint", None)
    return config_hash(plain)
