"""The executors' boundary (local, Ray, SLURM through submitit) and what a worker records: each
job runs under the driver's code and packages or is refused, its state lives under output_dir
wherever it runs, and its CPU reservation holds."""

import re
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.build import expand_jobs
from pipeline.experiment.executors import EXECUTOR_KINDS, Executor, make_executor
from pipeline.experiment.executors.worker import DriverIdentity, read_starts, run_here
from pipeline.experiment.records import RecordsFile
from tests.test_experiment import TINY, composed

BIN = Path(sys.executable).parent


def test_every_executor_kind_implements_the_one_boundary(tmp_path):
    for kind in EXECUTOR_KINDS:
        executor = make_executor({"kind": kind}, tmp_path)
        assert isinstance(executor, Executor), kind  # runtime-checkable protocol: map, slots, running
        assert callable(executor.map) and isinstance(executor.running, list)
    with pytest.raises(ValueError, match="local, ray, slurm"):
        make_executor({"kind": "kubernetes"}, tmp_path)


def test_job_folders_and_scene_paths_are_absolute_whatever_the_worker_cwd(tmp_path, monkeypatch):
    """A Ray worker started from another folder wrote job state under its own cwd (issue 45)."""
    monkeypatch.chdir(tmp_path)
    jobs = expand_jobs(composed(["experiment=debug", *TINY, "output_dir=relative/out"]))
    for job in jobs:
        assert Path(job.execution.job_dir).is_absolute()
        assert Path(job.execution.job_dir).is_relative_to(tmp_path / "relative" / "out")
        assert Path(job.scene_path).is_absolute()


def test_a_worker_under_other_code_or_packages_is_refused_and_not_retried(tmp_path):
    job = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", "job.retries=3",
                                f"output_dir={tmp_path}"]))[0]
    here = DriverIdentity.here()
    for expected, word in ((DriverIdentity("0123456789ab", here.packages), "code"),
                           (DriverIdentity(here.code_version, "feedfacecafe"), "packages")):
        outcome = run_here(job, None, None, expected)
        assert not outcome.finished and outcome.attempts == 1  # deterministic: no retry
        assert "refused" in outcome.traceback and word in outcome.traceback
        assert expected.code_version in outcome.traceback or expected.packages in outcome.traceback
    starts = read_starts(Path(job.execution.job_dir))
    assert len(starts) == 2 and all(s["pid"] == os.getpid() for s in starts)


def test_other_packages_name_what_differs_and_a_shared_environment_is_not_told_to_install(tmp_path, monkeypatch):
    """A shared environment being installed into while a launch starts: the node runs from the
    driver's own environment folder, so 'install requirements.lock on every node' is the wrong advice."""
    import sys
    from pipeline.experiment.executors.ray_cluster import driver_changed
    job = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", f"output_dir={tmp_path}"]))[0]
    here = DriverIdentity.here()
    assert "numpy" in here.pins and here.prefix == sys.prefix
    sent_pins = {**here.pins, "numpy": "0.0.1"}
    sent_pins.pop("scipy")
    shared = DriverIdentity(here.code_version, "feedfacecafe", sent_pins, sys.prefix)
    told = run_here(job, None, None, shared).traceback
    assert f"numpy {here.pins['numpy']} (driver 0.0.1)" in told and f"scipy {here.pins['scipy']} (driver missing)" in told
    assert "driver's environment folder" in told and "let the install finish" in told
    assert "install requirements.lock on every node" not in told
    elsewhere = DriverIdentity(here.code_version, "feedfacecafe", sent_pins, str(tmp_path / "other-venv"))
    assert "install requirements.lock on every node" in run_here(job, None, None, elsewhere).traceback
    assert driver_changed(here) == []  # the driver's packages as they were: nothing changed under it
    (line,) = driver_changed(shared)
    assert "changed since this launch began" in line and "numpy" in line
    from pipeline.experiment.executors import worker
    installed = dict(here.pins)
    monkeypatch.setattr(worker, "installed_pins", lambda: {**installed, "numpy": "0.0.2"})  # an install under way
    (line,) = driver_changed(here)  # read now, not the process's cached digest
    assert f"numpy 0.0.2 (driver {here.pins['numpy']})" in line


@pytest.mark.slow
def test_a_local_job_records_where_and_under_what_it_ran(tmp_path):
    from pipeline.experiment.provenance import code_version, environment
    from pipeline.experiment.sweep import run_sweep
    out = tmp_path / "o"
    summary = run_sweep(composed(["experiment=debug", *TINY, "method=[random]", "executor=local",
                                  "tracking=mlflow", f"output_dir={out}"]))
    final = RecordsFile(out).frame.query("kind == 'final'").iloc[0]
    from mlflow import MlflowClient
    tags = MlflowClient(summary.tracking_uri).get_run(final["run_id"]).data.tags
    assert tags["worker.node"] == "local" and tags["worker.packages"] == environment().packages
    assert tags["worker.starts"] == "1" and tags["worker.code_version"] == code_version()
    assert final["node"] == "local" and final["host"] == os.uname().nodename
    assert final["worker_code_version"] == code_version() and final["packages"] == environment().packages
    assert final["starts"] == 1 and final["elapsed_seconds"] >= final["wall_seconds"] > 0
    assert final["numerics"] == environment().numerics  # the code paths that move the digits


def test_the_numeric_code_paths_name_torch_mkl_and_numba_as_configured(monkeypatch):
    """What moves a result's last digits (reports/reproduce/README.md): torch's CPU capability,
    MKL's branch and numba's target CPU, each as this process has it."""
    import torch

    from pipeline.experiment.provenance import numeric_paths
    monkeypatch.delenv("MKL_CBWR", raising=False)
    monkeypatch.delenv("NUMBA_CPU_NAME", raising=False)
    import llvmlite.binding as llvm
    assert numeric_paths() == (f"torch {torch.backends.cpu.get_cpu_capability()}, MKL auto, "
                               f"numba {llvm.get_host_cpu_name()}")
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    monkeypatch.setenv("NUMBA_CPU_NAME", "haswell")
    assert numeric_paths().endswith(", MKL COMPATIBLE, numba haswell")


def test_the_environment_identity_follows_the_installed_packages(monkeypatch):
    from pipeline.experiment import provenance
    pins = provenance.installed_pins()
    assert "torch" in pins and "gopre" not in pins and "pip" not in pins
    lock = provenance.read_lock()
    assert provenance.lock_differences(pins, lock) == [], "this venv is not requirements.lock: run make env"
    assert provenance.environment().locked is True
    changed = {**pins, "numpy": "0.0.1"}
    assert provenance.lock_differences(changed, lock) == [f"numpy: locked {lock['numpy']}, installed 0.0.1"]
    assert provenance.lock_differences({**pins, "torch": lock["torch"] + "+cu124"}, lock) == []
    extra = {**pins, "left-pad": "1.0"}
    assert provenance.lock_differences(extra, lock) == ["left-pad: installed 1.0, not in the lock"]
    before = provenance.environment().packages
    monkeypatch.setattr(provenance, "installed_pins", lambda: changed)
    provenance.environment.cache_clear()
    try:
        assert provenance.environment().locked is False
        assert provenance.environment().packages != before  # another numpy: another identity
    finally:
        provenance.environment.cache_clear()


def test_the_lock_pins_every_declared_dependency_and_make_env_installs_it():
    import tomllib

    from pipeline.experiment.provenance import PACKAGE_ROOT, read_lock
    lock = read_lock()
    project = tomllib.loads((PACKAGE_ROOT / "pyproject.toml").read_text())["project"]
    declared = list(project["dependencies"])
    for extra in ("dev", "cluster", "server"):
        declared += [d for d in project["optional-dependencies"][extra] if not d.startswith("gopre[")]
    import re
    for requirement in declared:
        name = re.split(r"[\[<>=!~ ;]", requirement, maxsplit=1)[0].lower().replace("_", "-")
        assert name in lock, f"{name} ({requirement}) is not in requirements.lock: make lock"
    makefile = (PACKAGE_ROOT / "Makefile").read_text()
    assert "pip install -q -r requirements.lock" in makefile and "--no-deps -e ." in makefile
    dockerfile = (PACKAGE_ROOT / "docker" / "Dockerfile").read_text()
    assert "requirements.lock" in dockerfile


# --- Ray ---------------------------------------------------------------------------------------

def test_round_progress_survives_a_lost_inbox_and_posting_never_blocks(ray_session, capsys):
    from pipeline.experiment.executors.ray_cluster import RoundChannel
    from pipeline.experiment.outcome import StepProgress
    heard = []
    channel = RoundChannel(ray_session, [SimpleNamespace(config_hash="h")], lambda job, message: heard.append(message))
    assert ray_session.get(channel.inbox.node.remote()) == ray_session.get_runtime_context().get_node_id()  # on the driver's node
    step = StepProgress(0, 2, 5, 10, 1.0)
    ray_session.get(channel.inbox.post.remote("h", step.to_dict()))
    channel.drain()
    assert heard == [step]  # progress inside a round travels the same way
    heard.clear()

    @ray_session.remote(num_cpus=0)
    def post(inbox):
        inbox.post.remote("h", {"x": 1})  # what a task does: no ray.get
        return "posted"

    ray_session.kill(channel.inbox)  # the inbox is gone (its node lost, say)
    assert ray_session.get(post.remote(channel.inbox), timeout=60) == "posted"  # the task is not hurt
    channel.drain()
    channel.drain()  # said once, then quiet
    warnings = [ln for ln in capsys.readouterr().out.splitlines() if "round progress" in ln]
    assert len(warnings) == 1 and channel.lost is not None and heard == []
    channel.close()


def test_a_node_that_cannot_read_the_data_or_runs_other_code_is_named_before_any_job(ray_session, tmp_path):
    from pipeline.experiment.executors.ray_cluster import RayExecutor
    present = tmp_path / "a.png"
    present.write_bytes(b"x")
    scene = SimpleNamespace(splits={"train": SimpleNamespace(images=SimpleNamespace(paths=[present]))})
    executor = RayExecutor(output_dir=tmp_path / "out")
    executor.check_nodes(ray_session, {"s": scene}, DriverIdentity.here())  # all well: no error
    missing = SimpleNamespace(splits={"test": SimpleNamespace(images=SimpleNamespace(
        paths=[present, tmp_path / "gone.png"]))})
    with pytest.raises(ConfigError) as err:
        executor.check_nodes(ray_session, {"s": scene, "t": missing}, DriverIdentity("0123456789ab", "feedfacecafe"))
    text = str(err.value)
    node = ray_session.get_runtime_context().get_node_id()[:12]
    assert f"node {node}" in text and "cannot read 1 scene file(s), e.g. " + str(tmp_path / "gone.png") in text
    assert "code " in text and "0123456789ab" in text and "feedfacecafe" in text
    assert "no job was started" in text


def test_node_problems_name_a_node_without_the_shared_output_dir():
    from pipeline.experiment.executors.ray_cluster import node_problems
    report = {"node": "abcdef0123456789", "host": "w1", "missing": [], "missing_count": 0, "shared": False,
              "identity": None}
    (line,) = node_problems([report], Path("/shared/out"))
    assert line.startswith("node abcdef012345 (w1) does not see output_dir /shared/out")
    assert node_problems([{**report, "shared": True}], Path("/x")) == []


def test_a_cluster_that_refuses_the_driver_is_one_line_naming_the_token(monkeypatch):
    import socket

    from pipeline.experiment.executors.ray_cluster import connection_problem
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    for address in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}"):  # a GCS address and Ray Client's
        text = connection_problem(address, ConnectionError("Failed to connect"))
        assert "RAY_AUTH_MODE=token" in text and "auth_token" in text and "\n" not in text, address
    monkeypatch.setenv("RAY_AUTH_MODE", "token")  # the driver takes part: Ray's error is named, both causes said
    text = connection_problem(f"ray://127.0.0.1:{port}", ConnectionError("ray client connection timeout\nmore"))
    assert "could not join it (ray client connection timeout)" in text and "not be serving yet" in text
    assert "auth_token" in text and "\n" not in text
    listener.close()
    text = connection_problem(f"127.0.0.1:{port}", ConnectionError("Failed to connect"))
    assert "no Ray cluster answers" in text


SLOW_INBOX = """
import sys, time
from pipeline.experiment.executors import ray_cluster

class SlowInbox(ray_cluster.RoundInbox):  # defined here, so Ray ships it by value to its actor
    def post(self, config_hash, message):
        time.sleep(3)  # a busy driver node: a task that waited for this would block 3 s per round
        super().post(config_hash, message)

ray_cluster.RoundInbox = SlowInbox
from pipeline.cli.run import main
main()  # Hydra reads sys.argv
"""


@pytest.mark.slow
def test_a_one_cpu_ray_runs_one_job_at_a_time(tmp_path):
    """A round report was a blocking ray.get inside the task: Ray lent the blocked task's CPU to
    another, and a 1-CPU node ran two jobs at once (issue 45). Here the inbox answers slowly, so a
    task that waits for it blocks for seconds."""
    out = tmp_path / "o"
    script = tmp_path / "slow_inbox.py"
    script.write_text(SLOW_INBOX)
    proc = subprocess.run([sys.executable, str(script), "experiment=debug", *TINY, "protocol.budget=5",
                           "method=[random,coverage]", "executor=ray", "executor.num_cpus=1", "job.threads=1",
                           "tracking=none", f"output_dir={out}"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    finals = RecordsFile(out).frame.query("kind == 'final'")
    spans = []
    for _, row in finals.iterrows():
        (start,) = read_starts(out / "jobs" / row["config_hash"])
        spans.append((start["started"], start["started"] + row["elapsed_seconds"]))
        assert row["node"].startswith("ray:") and row["starts"] == 1
    (a0, a1), (b0, b1) = sorted(spans)
    assert a1 <= b0 + 0.5, f"two jobs ran at once on one CPU for {a1 - b0:.1f} s"


# --- SLURM through submitit (its local executor: the same array code, no SLURM) ----------------

@pytest.mark.slow
def test_a_slurm_array_sweep_equals_a_local_one(tmp_path):
    pytest.importorskip("submitit")
    from pipeline.experiment.sweep import run_sweep
    from tests.test_experiment import metrics_of
    common = ["experiment=debug", *TINY, "method=[random,coverage]", "tracking=none"]
    slurm = run_sweep(composed([*common, "executor=slurm", "executor.cluster=local",
                                f"output_dir={tmp_path / 'slurm'}"]))
    assert slurm.finished == 2 and slurm.failed == 0
    run_sweep(composed([*common, "executor=local", f"output_dir={tmp_path / 'local'}"]))
    array, here = RecordsFile(tmp_path / "slurm").frame, RecordsFile(tmp_path / "local").frame
    assert metrics_of(array) == metrics_of(here)
    assert set(array.query("kind == 'final'")["node"].str.split(":").str[0]) == {"submitit-local"}
    assert list((tmp_path / "slurm" / "slurm").iterdir()), "submitit's logs live under output_dir/slurm"
    again = run_sweep(composed([*common, "executor=slurm", "executor.cluster=local",
                                f"output_dir={tmp_path / 'slurm'}"]))
    assert again.skipped == 2 and again.finished == 0


@pytest.mark.slow
def test_a_preempted_array_task_is_requeued_and_resumes_from_its_checkpoint(tmp_path):
    """SLURM signals a task it preempts (or one near its time limit); submitit requeues it and the
    job goes on from its last round checkpoint. Here the task gets SLURM's signal (SIGUSR2) once
    the driver has heard its first round."""
    pytest.importorskip("submitit")
    import signal

    from pipeline.experiment.executors.slurm import SlurmExecutor
    from pipeline.experiment.sweep import validate_sweep
    overrides = ["experiment=debug", *TINY, "protocol.budget=6", "method=[random]", "splat.iterations=2400"]
    job = expand_jobs(composed([*overrides, f"output_dir={tmp_path / 'array'}"]))[0]
    validate_sweep([job])  # generates the scene the array task reads from its path
    executor = SlurmExecutor(tmp_path / "array", cluster="local", max_requeues=2, timeout_min=10)
    heard, outcomes, preempted = [], [], []

    def on_round(j, message):
        heard.append(message.record.round)
        if not preempted:
            (start,) = read_starts(Path(j.execution.job_dir))
            os.kill(start["pid"], signal.SIGUSR2)
            preempted.append(message.record.round)
    executor.map([job], {}, lambda j, outcome: outcomes.append(outcome), on_round)
    (outcome,) = outcomes
    assert outcome.finished, outcome.traceback
    assert outcome.worker["starts"] == 2  # preempted once, then requeued
    log = (Path(job.execution.job_dir) / "log.txt").read_text()
    assert "resuming from the checkpoint after" in log
    assert "failed" not in log  # the requeue signal ends the process, even inside a compiled kernel
    rounds = [r.round for r in outcome.episode.rounds]
    assert rounds == list(range(len(rounds))) and sorted(set(heard)) == rounds
    local = run_here(expand_jobs(composed([*overrides, f"output_dir={tmp_path / 'here'}"]))[0])
    assert outcome.final.psnr == local.final.psnr and outcome.episode.selected == local.episode.selected


def test_a_task_killed_once_says_one_start_and_where_it_ran(tmp_path):
    """A task that dies without returning (killed, out of memory): its attempts are the starts its
    job folder recorded, not 1 + max_requeues, and its record names the node it last ran on."""
    from pipeline.experiment.executors.slurm import SlurmExecutor
    from pipeline.experiment.executors.worker import record_start
    job = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", f"output_dir={tmp_path}"]))[0]

    class Killed:
        paths = None

        def result(self):
            raise RuntimeError("submitit: job 17 (task: 0) exited with signal 9 (SIGKILL)")
    executor = SlurmExecutor(tmp_path, cluster="local", max_requeues=3)
    never = executor._outcome(Killed(), job)
    assert never.attempts == 1 and "before the job started" in never.traceback and not never.worker
    record_start(Path(job.execution.job_dir))
    once = executor._outcome(Killed(), job)
    assert once.attempts == 1 and "after 1 start(s), the last on" in once.traceback and "SIGKILL" in once.traceback
    assert once.worker["starts"] == 1 and once.worker["host"] == os.uname().nodename
    from pipeline.experiment.records import worker_columns
    assert worker_columns(once)["starts"] == 1 and worker_columns(once)["elapsed_seconds"] >= 0


def test_the_sbatch_settings_are_ones_submitit_accepts(tmp_path, monkeypatch):
    submitit = pytest.importorskip("submitit")
    fake = tmp_path / "bin"  # submitit looks for srun before it takes settings; no job is submitted
    fake.mkdir()
    (fake / "srun").write_text("#!/bin/sh\nexit 1\n")
    (fake / "srun").chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake}:{os.environ['PATH']}")
    from pipeline.experiment.executors.slurm import SlurmExecutor
    jobs = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", "job.threads=4",
                                 f"output_dir={tmp_path}"]))
    executor = SlurmExecutor.from_config({"kind": "slurm", "partition": "cpu", "account": "lab", "timeout_min": 90,
                                          "array_parallelism": 8, "max_requeues": 2, "gpus_per_job": 1,
                                          "mem_gb": 32, "setup": ["module load cuda"], "signal_delay_s": 120},
                                         tmp_path)
    params = executor._slurm_parameters(jobs)
    assert params["cpus_per_task"] == 4 and params["slurm_partition"] == "cpu" and params["gpus_per_node"] == 1
    sbatch = submitit.AutoExecutor(folder=tmp_path / "s", cluster="slurm", slurm_max_num_timeout=2)
    sbatch.update_parameters(**params)  # submitit refuses an unknown or mistyped setting
    assert sbatch._executor.parameters["partition"] == "cpu"
    assert sbatch._executor.parameters["signal_delay_s"] == 120
    assert sbatch._executor.parameters["setup"] == ["module load cuda"]


def test_an_exit_inside_a_compiled_kernel_ends_the_job_instead_of_a_retry(tmp_path, monkeypatch):
    """A signal handler's SystemExit raised inside numba code arrives as a SystemError caused by it."""
    from pipeline.experiment import job as job_module
    job = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", "job.retries=2",
                                f"output_dir={tmp_path}"]))[0]

    def kernel_interrupted(*args, **kwargs):
        try:
            raise SystemExit(144)  # what submitit's handler does to requeue
        except SystemExit as exit_request:
            raise SystemError("CPUDispatcher(<composite_forward>) returned a result with an exception set") \
                from exit_request
    monkeypatch.setattr(job_module, "run_job", kernel_interrupted)
    with pytest.raises(SystemExit) as stopped:
        job_module.run_with_retries(job)
    assert stopped.value.code == 144
    def io_trouble(*args, **kwargs):
        raise OSError("a network file system hiccup")
    monkeypatch.setattr(job_module, "run_job", io_trouble)  # transient: retried
    outcome = job_module.run_with_retries(job)
    assert not outcome.finished and outcome.attempts == 3


@pytest.mark.parametrize("error", [ZeroDivisionError("division by zero"), TypeError("'>=' not supported"),
                                   ValueError("episode.pt: unreadable checkpoint"), FileNotFoundError("x.png")])
def test_a_deterministic_failure_is_not_retried(error, tmp_path, monkeypatch):
    from pipeline.experiment import job as job_module
    job = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", "job.retries=3",
                                f"output_dir={tmp_path}"]))[0]

    def fails(*args, **kwargs):
        raise error
    monkeypatch.setattr(job_module, "run_job", fails)
    outcome = job_module.run_with_retries(job)
    assert not outcome.finished and outcome.attempts == 1 and len(outcome.errors) == 1
    assert "deterministic: not retried" in (Path(job.execution.job_dir) / "log.txt").read_text()
    import logging
    assert not logging.getLogger(f"gopre.job.{Path(job.execution.job_dir).name}").handlers  # log file closed


def test_a_missing_kernel_cache_is_announced_and_compiled_before_any_job(tmp_path, monkeypatch, capsys):
    """A fresh clone spent 137-141 s silent after the launch: the driver now says it compiles the
    kernels, does it before any job (no job's timings carry it) and says how long it took."""
    from pipeline.experiment import warmup
    from pipeline.experiment.sweep import run_sweep
    monkeypatch.setattr(warmup, "kernels_cached", lambda: False)  # as on a fresh machine
    parts = []
    monkeypatch.setattr(warmup, "_run_parts", lambda say: parts.append(say))  # the parts: tested below
    monkeypatch.setattr(warmup.os, "sched_getaffinity", lambda pid: {0, 1})
    summary = run_sweep(composed(["experiment=debug", *TINY, "method=[random]", "executor=local",
                                  "tracking=none", f"output_dir={tmp_path}"]))
    lines = capsys.readouterr().out.splitlines()
    start = next(i for i, ln in enumerate(lines) if "compiling the CPU kernels for this machine, once" in ln)
    done = next(i for i, ln in enumerate(lines) if "compiled the CPU kernels in " in ln)
    first_job = next(i for i, ln in enumerate(lines) if "random on generated" in ln)
    assert start < done < first_job and summary.finished == 1 and len(parts) == 1
    assert "2 parts at once" in lines[done]
    monkeypatch.setattr(warmup, "kernels_cached", lambda: True)
    run_sweep(composed(["experiment=debug", *TINY, "method=[coverage]", "executor=local", "tracking=none",
                        f"output_dir={tmp_path / 'again'}"]))
    assert "compiling the CPU kernels" not in capsys.readouterr().out  # cached: nothing said, nothing run


@pytest.mark.parametrize("part", ["training", "selection"])
def test_each_part_of_the_parallel_compile_runs_on_its_own(part, monkeypatch):
    """The parallel compile's workers (``warmup --part NAME``) each run their paths (here from the
    cache); a part that failed would only be said and leave its kernels to the episode."""
    from pipeline.experiment import warmup
    ran = []
    original = warmup.PARTS[part]
    monkeypatch.setitem(warmup.PARTS, part, lambda: ran.append(part) or original())
    assert warmup.main(["--part", part]) == 0 and ran == [part]


def test_a_failed_part_is_said_and_the_rest_goes_on(monkeypatch):
    from pipeline.experiment import warmup
    said = []
    monkeypatch.setattr(warmup.sys, "executable", "false")  # every worker exits 1
    warmup._run_parts(said.append)
    assert said == [f"the kernels' {name} part failed (exit 1); the episode compiles what it left"
                    for name in warmup.PARTS]


def test_the_eta_comes_from_the_first_round_before_any_job_finishes(capsys):
    """No ETA until the first job finished (minutes at the paper preset): the rounds give one."""
    from pipeline.interchange.results import RoundRecord
    from pipeline.experiment.outcome import RoundMessage
    from pipeline.experiment.sweep import Progress
    jobs = [SimpleNamespace(config_hash=h, label=f"job {h}") for h in "abcd"]
    progress = Progress("s", total=4, slots=2)

    def heard(job, round_, seconds):
        record = RoundRecord(round=round_, num_views=2 + round_, iteration=0, test_psnr=20.0, test_ssim=0.5,
                             num_gaussians=10, train_seconds=seconds, selection_seconds=0.0)
        progress.round(job, RoundMessage(record, rounds=5, curve_views=8))
    heard(jobs[0], 0, 60.0)
    line = capsys.readouterr().out.strip().splitlines()[-1]
    # 4 jobs x 5 rounds, 1 heard: 19 rounds of 60 s on 2 slots = 9.5 min
    assert line.endswith("| sweep ETA 9.5 min (from the rounds so far)"), line
    heard(jobs[1], 0, 120.0)  # mean 90 s; 18 rounds left on 2 slots: 13.5 min
    assert capsys.readouterr().out.strip().endswith("sweep ETA 13.5 min (from the rounds so far)")


def test_progress_inside_a_round_reaches_the_console_and_the_job_log(tmp_path, capsys, monkeypatch):
    """At the paper preset a round is thousands of steps and a selection hundreds of Fisher views:
    a line at most every job.progress_seconds, for both."""
    from pipeline.acquisition import base
    from pipeline.experiment.executors.slurm import message_of, message_line
    from pipeline.experiment.outcome import StepProgress
    from pipeline.experiment.sweep import run_sweep
    monkeypatch.setattr(base, "FISHER_CHUNK", 2)  # the debug pool is smaller than one chunk
    run_sweep(composed(["experiment=debug", *TINY, "method=[fisherrf]", "splat.iterations=1200",
                        "job.progress_seconds=0.001", "executor=local", "tracking=none", f"output_dir={tmp_path}"]))
    out = capsys.readouterr().out.splitlines()
    lines = [ln for ln in out if "training step " in ln]
    assert lines and all("fisherrf on generated" in ln for ln in lines), lines
    scoring = [ln for ln in out if "selection, Fisher of " in ln]
    assert scoring and all(re.search(r"round \d/\d: selection, Fisher of \d+/\d+ views", ln) for ln in scoring), out
    log = next(tmp_path.glob("jobs/*/log.txt")).read_text()
    assert log.count("training step ") == len(lines) and log.count("selection, Fisher of ") == len(scoring)
    step = StepProgress(1, 3, 40, 120, 5.0)
    assert message_of(message_line(step)) == step  # the SLURM and Ray channels carry it as is
    assert step.text() == "round 2/3: training step 40/120 (5 s into the job)"
    assert StepProgress(2, 3, 1, 9, 0.0).text().startswith("final training: ")


def test_a_request_no_node_can_hold_is_refused_instead_of_waiting_forever(ray_session, tmp_path):
    """job.threads=1000 under Ray hung forever with no message (issue 47)."""
    from pipeline.experiment.executors.ray_cluster import RayExecutor, infeasible
    jobs = expand_jobs(composed(["experiment=debug", *TINY, "method=[random]", "job.threads=1000",
                                 f"output_dir={tmp_path}"]))
    with pytest.raises(ConfigError, match=r"job.threads=1000: no node of the cluster has that many CPUs "
                                          r"\(the largest has 2\)"):
        RayExecutor(output_dir=tmp_path, gpus_per_job=0).check_nodes(ray_session, {}, DriverIdentity.here(), jobs)
    nodes = [{"Resources": {"CPU": 8, "GPU": 1}}, {"Resources": {"CPU": 2}}]
    small = [SimpleNamespace(execution=SimpleNamespace(threads=8))]
    assert infeasible(small, nodes, 1) == []
    assert infeasible(small, nodes, 2) == ["executor.gpus_per_job=2: no node of the cluster has that many GPUs "
                                           "(the largest has 1); Ray would wait for one forever"]


class InlineExecutor:
    """A made-up executor for the registration test: its section and this class are all it takes."""

    slots = 1
    runs_here = True

    def __init__(self, workers: int):
        self.workers, self.running = workers, []

    @classmethod
    def from_config(cls, cfg: dict, output_dir):
        return cls(cfg.get("workers", 1))


def test_a_new_executor_is_its_section_and_its_class(tmp_path):
    """Registered by kind with its class: the schema checks and documents its keys, make_executor
    builds it, plan=true's estimate asks it how many jobs run at once."""
    from dataclasses import dataclass
    from typing import ClassVar

    from pipeline.bounds import INT, STR, bounded
    from pipeline.experiment.executors import config
    from pipeline.experiment.schema import config_problems, schema_rows

    @config.executor("inline", "tests.test_executors:InlineExecutor")
    @dataclass(frozen=True)
    class InlineSection:
        target: ClassVar[str]
        kind: str = bounded("inline", STR, choices=("inline",))
        workers: int = bounded(1, INT, ge=1)

        @staticmethod
        def slots(cfg: dict, threads: list[int]) -> int:
            return int(cfg.get("workers", 1))
    try:
        built = make_executor({"kind": "inline", "workers": 3}, tmp_path)
        assert type(built).__name__ == "InlineExecutor" and built.workers == 3  # (imported by its target)
        assert config.planned_slots({"kind": "inline", "workers": 3}, [1, 1]) == 3
        problems = config_problems({"executor": {"kind": "inline", "workers": 0}})
        assert any("executor.workers" in p for p in problems), problems
        assert not any("executor.kind" in p for p in problems)
        assert any("executor.(inline) workers" in str(row[0]) for row in schema_rows())
        with pytest.raises(ValueError, match="registered twice"):
            config.executor("inline", "x:Y")(InlineSection)
    finally:
        config.SECTIONS.pop("inline")
    with pytest.raises(ValueError, match="must be one of local, ray, slurm"):
        make_executor({"kind": "inline"}, tmp_path)
