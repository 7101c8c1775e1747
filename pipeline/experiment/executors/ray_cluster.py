"""``executor=ray``: one Ray task per job on a local Ray (this machine's cores) or a running cluster.

Each task reserves ``execution.threads`` CPUs (and ``gpus_per_job`` GPUs) and holds them: nothing
inside a task blocks on Ray (a blocked task lends its CPU to another task, so a 1-CPU node would
run two jobs at once). Scenes go into the object store once per (scene, resolution); the images
stay files, read by the node that runs the job, so every node must see the data and ``output_dir``
at the same paths (a shared filesystem): before any job starts, one probe per node checks that it
reads every scene file the jobs use, sees the driver's ``output_dir`` and runs the driver's code
and packages; a node that does not is named in one error.

A node lost mid-job: Ray reruns its task elsewhere (``max_retries``) and the job resumes from its
last round checkpoint under ``output_dir``. Round progress travels through a ``RoundInbox`` actor
pinned to the driver's own node (a lost worker node cannot take it along); tasks post to it
without waiting, and if it is gone anyway the driver says so once and goes on without round lines
(the outcomes carry every round).
"""

from __future__ import annotations

import os
import traceback
import uuid
from pathlib import Path

from pipeline.data.scene import Scene
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.console import console
from pipeline.experiment.executors.base import OnDone, OnRound, scene_key
from pipeline.experiment.executors.worker import DriverIdentity, identity_problem, pin_differences, run_here
from pipeline.experiment.interrupt import (SweepInterrupted, critical, current_handlers,
                                           install_stop_handlers, restore_handlers)
from pipeline.experiment.outcome import JobOutcome, RoundMessage, message_from_dict
from pipeline.experiment.spec import Job

POLL_SECONDS = 0.5  # how often the driver looks for round messages while jobs run
PROBE_TIMEOUT_S = 120  # a node that does not answer its probe in this time is named as unreachable
AUTH_HINT = ("the Ray cluster at {address} uses token authentication and this driver has no valid "
             "token: run with RAY_AUTH_MODE=token and the cluster's token (RAY_AUTH_TOKEN, or the "
             "file ~/.ray/auth_token of the head copied to this machine)")


def _remote_run(plain_job: dict, scene: Scene | None, expected: dict, inbox=None) -> dict:
    """A Ray task: the job arrives and the outcome leaves as plain data (``Job.to_dict``,
    ``JobOutcome.to_dict``). Round messages are posted to the inbox without waiting."""
    job = Job.from_dict(plain_job)
    report = None
    if inbox is not None:
        def report(message: RoundMessage) -> None:
            try:
                inbox.post.remote(job.config_hash, message.to_dict())  # fire and forget: no ray.get
            except Exception:  # progress is best effort; the outcome carries every round
                pass
    return run_here(job, scene, report, DriverIdentity(**expected)).to_dict()


class RoundInbox:
    """A Ray actor (0 CPUs) holding round messages until the driver takes them."""

    def __init__(self):
        self.messages: list[tuple[str, dict]] = []

    def post(self, config_hash: str, message: dict) -> None:
        self.messages.append((config_hash, message))

    def take(self) -> list[tuple[str, dict]]:
        out, self.messages = self.messages, []
        return out

    def node(self) -> str:
        import ray
        return ray.get_runtime_context().get_node_id()


def pinned_here(ray) -> dict:
    """Scheduling options that keep an actor on the driver's own node (hard affinity)."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
    return {"scheduling_strategy": NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(),
                                                                  soft=False)}


class RoundChannel:
    """Round messages from Ray tasks to the driver through a ``RoundInbox`` on the driver's node."""

    def __init__(self, ray, jobs: list[Job], on_round: OnRound):
        self.ray = ray
        self.inbox = ray.remote(num_cpus=0, **pinned_here(ray))(RoundInbox).remote()
        self.jobs = {job.config_hash: job for job in jobs}
        self.on_round = on_round
        self.lost: str | None = None  # why the inbox stopped answering

    def drain(self) -> None:
        if self.lost is not None:
            return
        try:
            with critical():  # Ray calls: a stop signal waits for them
                messages = self.ray.get(self.inbox.take.remote(), timeout=60)
        except Exception as err:  # the inbox died: the sweep goes on, without round lines
            self.lost = str(err).splitlines()[0][:200]
            console().warning(f"warning: round progress from the Ray tasks is lost ({self.lost}); the jobs "
                              "go on, and each job's rounds arrive with its result")
            return
        for config_hash, message in messages:
            self.on_round(self.jobs[config_hash], message_from_dict(message))

    def close(self) -> None:
        try:
            self.ray.kill(self.inbox)
        except Exception:  # already gone
            pass


def node_probe(paths: list[str], token_file: str, token: str, expected: dict) -> dict:
    """Runs on one node: what it cannot read, whether it sees the driver's output_dir, its identity."""
    import socket

    import ray
    missing = [p for p in paths if not os.access(p, os.R_OK)]
    try:
        shared = Path(token_file).read_text() == token
    except OSError:
        shared = False
    return {"node": ray.get_runtime_context().get_node_id(), "host": socket.gethostname(),
            "missing": missing[:3], "missing_count": len(missing), "shared": shared,
            "identity": identity_problem(DriverIdentity(**expected))}


def driver_changed(expected: DriverIdentity) -> list[str]:
    """A line when the driver's own packages changed since the launch began (an install into its
    environment under way): no node can match what it was sent."""
    now = DriverIdentity.here()
    if now.packages == expected.packages:
        return []
    return [f"the driver's own packages changed since this launch began ({pin_differences(expected.pins, now.pins)}): "
            "an install into its environment is under way or just ended: let it finish and launch again"]


def infeasible(jobs: list[Job], nodes: list[dict], gpus_per_job: float) -> list[str]:
    """One line per resource request no alive node can ever hold (Ray would wait for it forever,
    silently): a job's ``job.threads`` CPUs, or ``executor.gpus_per_job`` GPUs."""
    most_cpus = max((n.get("Resources", {}).get("CPU", 0) for n in nodes), default=0)
    most_gpus = max((n.get("Resources", {}).get("GPU", 0) for n in nodes), default=0)
    problems = []
    threads = max((j.execution.threads for j in jobs), default=0)
    if threads > most_cpus:
        problems.append(f"job.threads={threads}: no node of the cluster has that many CPUs (the largest has "
                        f"{most_cpus:g}); Ray would wait for one forever")
    if gpus_per_job > most_gpus:
        problems.append(f"executor.gpus_per_job={gpus_per_job:g}: no node of the cluster has that many GPUs (the "
                        f"largest has {most_gpus:g}); Ray would wait for one forever")
    return problems


def scene_files(scenes: dict[str, Scene]) -> list[str]:
    """Every file the scenes' images are read from (each node must read them)."""
    files = set()
    for scene in scenes.values():
        for split in scene.splits.values():
            files.update(str(Path(p).resolve()) for p in getattr(split.images, "paths", []))
    return sorted(files)


def node_problems(reports: list[dict], output_dir: Path) -> list[str]:
    """One line per node that cannot run the sweep's jobs, from the probes' reports."""
    problems = []
    for r in reports:
        where = f"node {r['node'][:12]} ({r['host']})"
        if r["missing_count"]:
            problems.append(f"{where} cannot read {r['missing_count']} scene file(s), e.g. {r['missing'][0]}: "
                            "every node needs the data at the same path (a shared filesystem), or run "
                            "without that node")
        if not r["shared"]:
            problems.append(f"{where} does not see output_dir {output_dir}: job folders (checkpoints that "
                            "let a retried job resume) must be on a filesystem every node shares")
        if r["identity"]:
            problems.append(f"{where}: {r['identity']}")
    return problems


class RayExecutor:
    def __init__(self, address: str | None = None, num_cpus: int | None = None, gpus_per_job: float = 0,
                 max_retries: int = 2, output_dir: Path | None = None):
        self.address, self.num_cpus = address, num_cpus
        self.gpus_per_job, self.max_retries = gpus_per_job, max_retries
        self.output_dir = Path(output_dir).resolve() if output_dir is not None else None
        self.slots = 1
        self.running: list[Job] = []  # the jobs a stop signal interrupted (see SweepInterrupted)
        self.runs_here = not address  # a Ray this launch starts on this machine's cores

    @classmethod
    def from_config(cls, cfg: dict, output_dir: Path) -> "RayExecutor":
        return cls(cfg.get("address"), cfg.get("num_cpus"), cfg.get("gpus_per_job", 0), cfg.get("max_retries", 2),
                   Path(output_dir))

    def _start(self):
        """Ray, and whether this call started it (then ``map`` shuts it down again)."""
        import ray

        if ray.is_initialized():  # e.g. a test session's shared Ray
            return ray, False
        if self.address:
            if self.address.startswith("ray://"):
                _require_client()
            try:
                ray.init(address=self.address, include_dashboard=False, log_to_driver=False)
            except ConnectionError as err:  # after Ray's own 20 s of retries
                raise ConfigError(connection_problem(self.address, err)) from None
        else:
            # address="local": always a fresh local instance, never a stale cluster address file
            ray.init(address="local", num_cpus=self.num_cpus or os.cpu_count(), include_dashboard=False,
                     log_to_driver=False)
        return ray, True

    def check_nodes(self, ray, scenes: dict[str, Scene], expected: DriverIdentity,
                    jobs: list[Job] | None = None) -> None:
        """One probe per alive node with CPUs; a ConfigError naming every node that cannot run jobs,
        and every resource request no node can hold."""
        too_big = infeasible(jobs or [], [n for n in ray.nodes() if n.get("Alive")], self.gpus_per_job)
        if too_big:
            raise ConfigError(f"{len(too_big)} problem(s) with the Ray cluster's resources, no job was started:\n  "
                              + "\n  ".join(too_big))
        if self.output_dir is None:
            return
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
        marker = self.output_dir / ".nodes" / uuid.uuid4().hex
        marker.parent.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex
        marker.write_text(token)
        reports: list[dict] = []
        try:
            probe = ray.remote(num_cpus=0, max_retries=0)(node_probe)
            nodes = [n for n in ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) > 0]
            files = scene_files(scenes)
            refs = {probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False))
                    .remote(files, str(marker), token, expected.to_dict()): n for n in nodes}
            ready, waiting = ray.wait(list(refs), num_returns=len(refs), timeout=PROBE_TIMEOUT_S)
            problems = []
            for ref in ready:
                try:
                    reports.append(ray.get(ref))
                except Exception as err:
                    problems.append(f"node {refs[ref]['NodeID'][:12]} ({refs[ref].get('NodeManagerAddress')}): "
                                    f"its probe failed: {str(err).splitlines()[0][:200]}")
            problems += [f"node {refs[r]['NodeID'][:12]} ({refs[r].get('NodeManagerAddress')}) did not answer its "
                         f"probe in {PROBE_TIMEOUT_S} s" for r in waiting]
            problems += node_problems(reports, self.output_dir)
        finally:
            marker.unlink(missing_ok=True)
        if any(r.get("identity") for r in reports):
            problems += driver_changed(expected)
        if problems:
            raise ConfigError(f"{len(problems)} problem(s) with the Ray cluster's nodes, no job was started:\n  "
                              + "\n  ".join(problems))

    def map(self, jobs: list[Job], scenes: dict[str, Scene], on_done: OnDone,
            on_round: OnRound | None = None) -> None:
        previous = current_handlers()  # restored when the sweep ends
        ray, started_here, channel, pending = None, False, None, {}
        expected = DriverIdentity.here()
        try:
            # Every Ray call runs with stop signals deferred (``critical``): a handler that raised
            # inside Ray's Cython code would surface as a SystemError instead of a clean stop, and
            # one inside ray.init left a half-started Ray that crashed the exit; the request is
            # acted on as soon as the call returns (at most one poll later).
            with critical():
                ray, started_here = self._start()
                install_stop_handlers()  # after ray.init, which installs its own SIGTERM handler
                self.check_nodes(ray, scenes, expected, jobs)
                channel = RoundChannel(ray, jobs, on_round) if on_round is not None else None
                refs = {key: ray.put(scene) for key, scene in scenes.items()}  # once per scene
            cpus = ray.cluster_resources().get("CPU", 1)
            self.slots = max(1, int(cpus // max(1, min(j.execution.threads for j in jobs)))) if jobs else 1
            task = ray.remote(_remote_run)
            with critical():
                for job in jobs:
                    options = {"num_cpus": job.execution.threads, "num_gpus": self.gpus_per_job,
                               "max_retries": self.max_retries, "name": f"{job.method}:{job.scene}"}
                    inbox = channel.inbox if channel is not None else None
                    ref = task.options(**options).remote(job.to_dict(), refs.get(scene_key(job)),
                                                         expected.to_dict(), inbox)
                    pending[ref] = job
            while pending:
                with critical():
                    done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_SECONDS)
                if channel is not None:  # a job's rounds are all heard before its end
                    channel.drain()
                if not done:
                    continue
                job = pending.pop(done[0])
                try:
                    with critical():
                        outcome = JobOutcome.from_dict(ray.get(done[0]))
                except Exception:  # the worker died more often than max_retries allows
                    outcome = JobOutcome.failed(self.max_retries + 1, [traceback.format_exc()])
                on_done(job, outcome)
        except SweepInterrupted:
            self.running = self._cancel(ray, pending) if ray is not None else []
            raise
        finally:
            if channel is not None:
                channel.close()
            if started_here:
                ray.shutdown()
            restore_handlers(previous)  # the caller's handlers (the CLI's own, or a test runner's)

    @staticmethod
    def _cancel(ray, pending: dict) -> list[Job]:
        """Cancel every pending task (force: the worker processes stop); returns the jobs that
        had started (those that never started are simply not run)."""
        started = []
        for ref, job in pending.items():
            try:
                ray.cancel(ref, force=True)
            except Exception:  # already finished or gone: nothing to stop
                pass
            if Path(job.execution.job_dir).exists():  # run_job made its folder: it started
                started.append(job)
        return started


def connection_problem(address: str, err: BaseException) -> str:
    """One line for a cluster Ray could not join: nothing listens there, or (something answers,
    yet Ray was refused) token authentication that this driver does not take part in."""
    host, _, port = address.split("://", 1)[-1].rpartition(":")  # ray://host:10001 (Ray Client) or host:6379
    listening = False
    if port.isdigit() and host:
        import socket
        try:
            socket.create_connection((host, int(port)), timeout=3).close()
            listening = True
        except OSError:
            listening = False
    if listening and os.environ.get("RAY_AUTH_MODE", "").lower() != "token":
        return "executor.address: " + AUTH_HINT.format(address=address)
    if listening:  # a token that differs, or a head whose Ray Client server is not serving yet: Ray says the same
        return (f"executor.address: something listens at {address} but Ray could not join it "
                f"({str(err).splitlines()[0][:150]}): a cluster started seconds ago may not be serving yet (try "
                f"again); else, with RAY_AUTH_MODE=token, its token differs from the head's (RAY_AUTH_TOKEN or "
                f"~/.ray/auth_token)")
    return (f"executor.address: no Ray cluster answers at {address} ({str(err).splitlines()[0][:150]}): start "
            f"one (ray start --head --port=...) or use executor.address=null for a local Ray")


def _require_client() -> None:
    try:
        import ray.util.client  # noqa: F401
        import grpc  # noqa: F401  (what ray[client] adds)
    except ImportError:
        raise ConfigError("executor.address=ray://...: Ray Client needs the cluster extra: "
                          "pip install 'gopre[cluster]' (ray[client,default], submitit)") from None
