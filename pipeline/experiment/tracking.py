"""Tracking: MLflow (one parent run per sweep launch, one child run per job) or none.

Only the driver talks to MLflow. The default store is embedded: ``sqlite:///<output_dir>/mlflow.db``
with artifacts under ``<output_dir>/mlartifacts`` (no server); ``uri=http://host:port`` logs to a
tracking server. Child runs carry the tags method, dataset, scene, protocol, seed, config_hash and
``mlflow.parentRunId``; params are the flattened job config; per-round metrics use step = number
of views, so the UI draws PSNR-vs-views curves. A job's child run opens with its first round
message (``log_round``, while the job runs) and is completed by ``log_job`` when it ends.

With a server (``uri=http://...``) the artifacts go through it when it serves them (``mlflow server
--artifacts-destination ...``: ``mlflow-artifacts:/`` locations), so every client sees them; a
server started with ``--default-artifact-root DIR`` instead makes each client write DIR itself.
The driver says so, once, when the experiment's artifact location is a plain path or file URI.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Protocol, runtime_checkable

from pipeline.interchange.results import RoundRecord
from pipeline.experiment.records import SEARCH_TAKEN_CODES, depth_columns, uncertainty_columns
from pipeline.experiment.record_columns import final_metrics, final_tags
from pipeline.experiment.record_columns import round_metrics as recorded_round_metrics
from pipeline.experiment.console import console
from pipeline.experiment.outcome import JobOutcome, RoundMessage
from pipeline.experiment.provenance import code_version
from pipeline.experiment.spec import Job
from pipeline.interchange.layout import SweepFolder

TAGS = ("method", "dataset", "scene", "seed", "config_hash", "strategy", "kind", "setting", "code_version",
        "data_fingerprint")


def flatten(data: dict, prefix: str = "") -> dict[str, str]:
    out = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = str(value)[:500]
    return out


def plugin_tags(job: Job) -> dict[str, str]:
    """A plugin strategy's identity as tags (plugin, plugin_distribution, plugin_version,
    plugin_sha256); none for a built-in strategy."""
    if job.plugin is None:
        return {}
    p = job.plugin
    return {"plugin": str(p["reference"]), "plugin_distribution": str(p["distribution"]),
            "plugin_version": str(p["version"]), "plugin_sha256": str(p["source_sha256"])}


def job_params(job: Job) -> dict[str, str]:
    return flatten({k: v for k, v in job.to_dict().items()
                    if k not in ("execution", "config_hash", "sweep", "code_version")})


def round_metrics(r: RoundRecord) -> list[tuple[str, float, int]]:
    """The metrics of one round record (or live round message), at step = views trained on: its
    recorded fields (``record_columns``; ``test_ssim`` is 3DGS's SSIM, ``test_ssim_skimage``
    scikit-image's; None is not logged), then a search's account off the pool."""
    step = r.num_views
    out = recorded_round_metrics(r)
    if r.search:  # a round off the pool (records.SEARCH_METRICS reads these back)
        out += [(f"search_{key}", r.search[key], step) for key in ("score", "best_start_score",
                                                                   "best_pool_score", "evaluations", "seconds")]
        out.append(("search_taken", SEARCH_TAKEN_CODES[r.search["taken"]], step))
    return out


@runtime_checkable
class Tracker(Protocol):
    """What the sweep driver tells its tracking store (two implementations: ``MlflowTracker``,
    ``NoTracker``). ``uri``: where it is (None: nowhere)."""

    uri: str | None

    def finished_hashes(self) -> set[str]: ...
    def start(self, sweep_config: dict, jobs: int) -> None: ...
    def log_round(self, job: Job, message: RoundMessage) -> None: ...
    def log_job(self, job: Job, outcome: JobOutcome) -> str | None: ...
    def end(self, summary: dict) -> None: ...
    def interrupt(self, summary: dict) -> None: ...
    def close_stale_runs(self) -> list[str]: ...
    def answers(self) -> bool: ...
    def close_orphans(self) -> None: ...


class NoTracker:
    uri = None

    def finished_hashes(self) -> set[str]:
        return set()

    def start(self, sweep_config: dict, jobs: int) -> None:
        pass

    def log_round(self, job: Job, message: RoundMessage) -> None:
        pass

    def log_job(self, job: Job, outcome: JobOutcome) -> str | None:
        return None

    def end(self, summary: dict) -> None:
        pass

    def interrupt(self, summary: dict) -> None:
        pass

    def close_stale_runs(self) -> list[str]:
        return []

    def answers(self) -> bool:
        return True

    def close_orphans(self) -> None:
        pass


REACH_TIMEOUT_S = 5.0
HTTP_LIMITS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
               "MLFLOW_HTTP_REQUEST_TIMEOUT": "30"}  # overridable from the environment


def check_reachable(uri: str, timeout: float = REACH_TIMEOUT_S) -> None:
    """A tracking server URI must answer (any HTTP status) before a sweep starts; otherwise one
    clear ConfigError instead of minutes of client retries."""
    import urllib.error
    import urllib.request

    from pipeline.experiment.episode_settings import ConfigError
    if not uri.startswith(("http://", "https://")):
        return
    try:
        urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=timeout).close()
    except urllib.error.HTTPError:
        return  # it answered
    except (urllib.error.URLError, OSError) as err:
        reason = getattr(err, "reason", err)
        raise ConfigError(f"tracking.uri {uri} cannot be reached ({reason}): start the server "
                          f"(mlflow server --host ... --port ...), or run with tracking=none, or use the "
                          f"embedded store under output_dir (tracking.uri=null)") from None


class MlflowTracker:
    def __init__(self, uri: str | None, output_dir: Path, experiment: str):
        from mlflow import MlflowClient

        if uri:
            check_reachable(uri)
            # a server that goes away mid-sweep must cost seconds per call, not MLflow's default
            # minutes of retries: the records keep everything and tracking_sync=true replays it
            for key, value in HTTP_LIMITS.items():
                os.environ.setdefault(key, value)

        output_dir = Path(output_dir).resolve()
        output_dir.mkdir(parents=True, exist_ok=True)
        self.output_dir = str(output_dir)  # tagged on every run: whose sweep a run belongs to
        self.uri = uri or f"sqlite:///{output_dir / 'mlflow.db'}"
        self.shared = bool(uri)  # a server other folders' sweeps write to as well
        self.client = MlflowClient(tracking_uri=self.uri)
        self.experiment_id = self._experiment(experiment, None if uri else (output_dir / "mlartifacts").as_uri())
        if uri:
            self._say_where_artifacts_go()
        self.parent: str | None = None
        # config hash -> (child run opened by a round message, steps (views) it has logged)
        self.live: dict[str, tuple[str, set[int]]] = {}
        self.imaged: dict[str, set[int]] = {}  # config hash -> steps whose round images MLflow received live
        self.orphans: list[str] = []  # child runs a failed call left open (an outage): KILLED once it answers

    def _experiment(self, name: str, location: str | None) -> str:
        """The experiment's id, created if needed; two sweeps creating it at once both get it."""
        found = self.client.get_experiment_by_name(name)
        if found is not None:
            return found.experiment_id
        try:
            return self.client.create_experiment(name, artifact_location=location)
        except Exception:  # created meanwhile by a concurrent sweep on the same server
            found = self.client.get_experiment_by_name(name)
            if found is None:
                raise
            return found.experiment_id

    def _say_where_artifacts_go(self) -> None:
        location = self.client.get_experiment(self.experiment_id).artifact_location or ""
        if not location.startswith(("mlflow-artifacts:", "s3://", "gs://", "wasbs://", "hdfs://")):
            console().warning(f"warning: the tracking server stores this experiment's artifacts at {location}, "
                              "a path each client writes itself: clients on other machines will not see them. "
                              "Start the server with --artifacts-destination DIR_OR_S3 (proxied artifacts), "
                              "as docker/compose.yaml does")

    def finished_hashes(self) -> set[str]:
        """The config hashes this output folder finished, as the tracking store has them. On a
        shared server (``tracking.uri``) only the runs tagged with this folder count: another
        folder's finished runs of the same configs must not empty this sweep (its records and job
        folders would never be written). The embedded store under the folder is the folder's own
        (runs are counted whatever path they were tagged with, so a moved folder still resumes)."""
        hashes, token = set(), None
        while True:
            page = self.client.search_runs([self.experiment_id], "attributes.status = 'FINISHED'",
                                           max_results=1000, page_token=token)
            hashes |= {r.data.tags["config_hash"] for r in page if "config_hash" in r.data.tags
                       and (not self.shared or r.data.tags.get("output_dir") == self.output_dir)}
            token = page.token
            if not token:
                return hashes

    def start(self, sweep_config: dict, jobs: int) -> None:
        run = self.client.create_run(self.experiment_id, run_name=f"sweep {time.strftime('%Y-%m-%d %H:%M:%S')}",
                                     tags={"kind": "sweep", "jobs": str(jobs), "output_dir": self.output_dir,
                                           "code_version": code_version()})
        self.parent = run.info.run_id
        self._log_params(self.parent, flatten(sweep_config))

    def _log_params(self, run_id: str, params: dict[str, str]) -> None:
        from mlflow.entities import Param

        items = [Param(k[:250], v) for k, v in sorted(params.items())]
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i:i + 100])

    def _log_metrics(self, run_id: str, metrics: list[tuple[str, float, int]]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v, step in metrics
                 if v is not None and math.isfinite(float(v))]
        for i in range(0, len(items), 1000):
            self.client.log_batch(run_id, metrics=items[i:i + 1000])

    def _child_run(self, job: Job, started: float | None = None) -> str:
        """A new child run for ``job``, with its tags and params, starting when the job started
        (``started``, seconds since the epoch; None: now)."""
        tags = {k: str(getattr(job, k)) for k in TAGS}
        tags["data_fingerprint"] = str(job.data_identity or "")
        tags.update({"protocol": job.protocol["kind"], "mlflow.parentRunId": self.parent or "",
                     "output_dir": self.output_dir})
        tags.update(plugin_tags(job))
        run = self.client.create_run(self.experiment_id, run_name=f"{job.method} {job.scene} s{job.seed}",
                                     tags=tags, start_time=int(started * 1000) if started else None)
        self._log_params(run.info.run_id, job_params(job))
        return run.info.run_id

    def log_round(self, job: Job, message: RoundMessage) -> None:
        """A round of a running job: its metrics at step = views, in the job's (open) child run."""
        if job.config_hash not in self.live:
            self.live[job.config_hash] = (self._child_run(job, message.job_started), set())
        run_id, logged = self.live[job.config_hash]
        self._log_metrics(run_id, round_metrics(message.record))
        logged.add(message.record.num_views)
        self._log_images(run_id, message.images, message.record.num_views)
        if message.images:
            self.imaged.setdefault(job.config_hash, set()).add(message.record.num_views)

    def _log_images(self, run_id: str, images: dict[str, bytes], step: int) -> None:
        import io

        from PIL import Image
        for key, png in images.items():  # MLflow's image series per step
            self.client.log_image(run_id, Image.open(io.BytesIO(png)), key=key, step=step)

    def _log_saved_round_images(self, run_id: str, job: Job, live: bool) -> int:
        """The round images the job saved in its folder (``JobFolder.round_images``) that this run did
        not receive live (a lost progress channel, a replay); how many steps were taken from there.
        A run that is not the live one (a replay's) received none: what was imaged live went to the
        run the outage left open, which ends KILLED."""
        imaged_live = self.imaged.pop(job.config_hash, set())
        received = imaged_live if live else set()
        saved = SweepFolder(Path(self.output_dir)).job(job.config_hash).saved_round_images()
        missing = {step: files for step, files in saved.items() if step not in received}
        for step, files in sorted(missing.items()):
            self._log_images(run_id, {key: path.read_bytes() for key, path in files.items()}, step)
        return len(missing)

    def log_job(self, job: Job, outcome: JobOutcome) -> str:
        """Complete the job's child run (the live one, else a new one) with its final state."""
        live = job.config_hash in self.live
        run_id, logged = (self.live.pop(job.config_hash, None)
                          or (self._child_run(job, outcome.worker.get("first_started")), set()))
        try:
            self._complete(run_id, logged, job, outcome, live)
        except Exception:
            self.orphans.append(run_id)  # left open by the failure: ended KILLED once the store answers
            raise
        return run_id

    def _complete(self, run_id: str, logged: set[int], job: Job, outcome: JobOutcome, live: bool) -> None:
        tags = {"attempts": str(outcome.attempts)}
        w = outcome.worker  # where and under what it ran (executors.worker), as the records have it
        tags.update({f"worker.{k}": str(w[k]) for k in ("host", "node", "code_version", "packages", "locked",
                                                         "cpu", "starts") if k in w})
        final = outcome.final
        if final is not None:  # degraded, lpips_status, metrics_version (what final_ssim means) ...
            tags.update(final_tags(final))
        poses = json.dumps(outcome.episode.acquired_poses) if outcome.episode is not None else "null"
        if poses not in ("null", "[]") and len(poses) <= 5000:  # the views captured off the pool (a tag's limit;
            tags["acquired_poses"] = poses                          # result.json, an artifact, has them all)
        if job.index is not None:  # the config's job order, which the report keeps
            tags["job_index"] = str(job.index)
        for key, value in tags.items():
            self.client.set_tag(run_id, key, value)
        if outcome.finished:
            self._log_metrics(run_id, self._metrics(job, outcome, logged))
            taken = self._log_saved_round_images(run_id, job, live)
            if taken and live:  # a replay takes them all from there: nothing to say
                console().info(f"{job.label}: the round images of {taken} round(s) taken from its job folder "
                               "(MLflow did not receive them while it ran)")
        self._log_artifacts(run_id, job, outcome)
        self.client.set_terminated(run_id, outcome.status)

    @staticmethod
    def _metrics(job: Job, outcome: JobOutcome,
                 logged: set[int] = frozenset()) -> list[tuple[str, float, int]]:
        """Final metrics, and the round metrics of steps not already logged live."""
        if job.kind == "uncertainty":
            return [(f"ause_{name}", v, 0) for name, v in outcome.uncertainty.ause.items()]
        episode = outcome.episode
        out = [m for r in episode.rounds if r.num_views not in logged for m in round_metrics(r)]
        final = episode.final
        out += final_metrics(final) + [("wall_seconds", outcome.seconds, 0)]
        # the families records_from_mlflow reads back by prefix (records.TRACKED_METRIC_PREFIXES)
        out += [(k, v, 0) for k, v in {**uncertainty_columns(final.uncertainty), **depth_columns(final.depth)}.items()]
        return out

    def _log_artifacts(self, run_id: str, job: Job, outcome: JobOutcome) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            (folder / "config.json").write_text(json.dumps(job.to_dict(), indent=1))
            if outcome.result is not None:
                (folder / "result.json").write_text(json.dumps(outcome.result, default=str))
            for name, data in outcome.artifacts.items():
                path = folder / name
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            self.client.log_artifacts(run_id, str(folder))

    def answers(self) -> bool:
        """Whether the store answers now (a server: its /health; the embedded store: always)."""
        try:
            check_reachable(self.uri)
        except Exception:
            return False
        return True

    def close_orphans(self) -> None:
        """End KILLED the child runs an outage left open (their jobs are replayed as new runs)."""
        for run_id in list(self.orphans):
            try:
                self.client.set_terminated(run_id, "KILLED")
            except Exception:
                continue
            self.orphans.remove(run_id)

    def close_stale_runs(self) -> list[str]:
        """Runs of this output folder left RUNNING by a driver that was killed (its lock was
        stale): they end KILLED. Runs of other folders on the same server are not touched."""
        stale, token = [], None
        while True:
            page = self.client.search_runs([self.experiment_id], "attributes.status = 'RUNNING'",
                                           max_results=1000, page_token=token)
            stale += [r.info.run_id for r in page if r.data.tags.get("output_dir") == self.output_dir]
            token = page.token
            if not token:
                break
        for run_id in stale:
            self.client.set_terminated(run_id, "KILLED")
        return stale

    def interrupt(self, summary: dict) -> None:
        """A stop signal: the child runs of interrupted jobs and the parent run end KILLED."""
        for run_id, _ in self.live.values():
            self.client.set_terminated(run_id, "KILLED")
        self.live.clear()
        if self.parent is not None:
            self._log_metrics(self.parent, [(k, v, 0) for k, v in summary.items()
                                            if isinstance(v, (int, float)) and not isinstance(v, bool)])
            self.client.set_terminated(self.parent, "KILLED")

    def end(self, summary: dict) -> None:
        if self.parent is None:
            return
        self._log_metrics(self.parent, [(k, v, 0) for k, v in summary.items() if isinstance(v, (int, float))])
        try:
            self._log_sweep_figures()
        except Exception as err:  # a figure must not keep the sweep's run open
            console().warning(f"warning: the sweep's figures were not logged to MLflow: "
                              f"{str(err).splitlines()[0][:300]}")
        self.client.set_terminated(self.parent, "FAILED" if summary.get("failed") else "FINISHED")

    def _log_sweep_figures(self) -> None:
        """The report's figures of the sweep's records (PSNR curves, the qualitative grid with the
        ground truth once per view, uncertainty maps) as the parent run's ``figures/``."""
        from pipeline.report.report import load_records, make_figures  # the reporting edge
        try:
            frame = load_records(self.output_dir)
        except (FileNotFoundError, ValueError):
            return
        with tempfile.TemporaryDirectory() as tmp:
            if make_figures(frame, Path(self.output_dir), Path(tmp)):
                self.client.log_artifacts(self.parent, str(Path(tmp) / "figures"), "figures")


def make_tracker(cfg: dict, output_dir: Path, experiment: str) -> Tracker:
    kind = cfg.get("kind")
    if kind == "none":
        return NoTracker()
    if kind == "mlflow":
        return MlflowTracker(cfg.get("uri"), output_dir, experiment)
    raise ValueError(f"tracking.kind: must be 'mlflow' or 'none', got {kind!r}")


def mlflow_runs_hint(uri: str | None, experiment_id: str | None) -> str | None:
    """How to open a sweep's runs in the MLflow UI, with the runs page's address (MLflow 3
    otherwise opens on its GenAI page): a served store's URL, or the ``mlflow ui`` command for
    a local store. None without tracking."""
    if not uri or experiment_id is None:
        return None
    page = f"#/experiments/{experiment_id}/runs"
    if uri.startswith(("http://", "https://")):
        return f"MLflow runs: {uri.rstrip('/')}/{page}"
    return (f"MLflow runs: mlflow ui --backend-store-uri {uri} --port 5000, then open "
            f"http://127.0.0.1:5000/{page}")

