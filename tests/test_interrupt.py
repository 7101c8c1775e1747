"""Stopping the real ``pipeline-run`` driver of a Ray sweep with SIGINT (Ctrl-C) or SIGTERM: it
stops within seconds with 128 + the signal, finished jobs stay recorded, MLflow keeps no run
RUNNING, and the same command resumes to the results of an uninterrupted sweep."""

import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pipeline.experiment.records import RecordsFile

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
SWEEP = ["experiment=debug", "seeds=[0,1]", "splat.iterations=160", "dataset.generated.generate.size=32",
         "job.retries=0"]


def start(out: Path, *extra, cpus: int = 2) -> tuple[subprocess.Popen, "queue.Queue[str]"]:
    proc = subprocess.Popen([str(BIN / "pipeline-run"), *SWEEP, "executor=ray", f"executor.num_cpus={cpus}",
                             "tracking=mlflow", f"output_dir={out}", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: "queue.Queue[str]" = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True)
    reader.start()
    lines.reader = reader  # drain() waits for it: the last lines may still be in the pipe when the driver exits
    return proc, lines


def wait_for(lines, text: str, timeout: float) -> list[str]:
    seen, end = [], time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            line = lines.get(timeout=1)
        except queue.Empty:
            continue
        seen.append(line)
        if text in line:
            return seen
    raise AssertionError(f"no line with {text!r} within {timeout} s; got:\n" + "".join(seen))


def drain(lines) -> str:
    """Every line so far; once the driver has exited, every line it printed (the reader reaches EOF)."""
    reader = getattr(lines, "reader", None)
    deadline = time.monotonic() + 60
    while reader is not None and reader.is_alive() and time.monotonic() < deadline:
        before = lines.qsize()
        reader.join(3.0)  # EOF; or, where a Ray process still holds the pipe, 3 s without a new line
        if lines.qsize() == before:
            break
    out = []
    while not lines.empty():
        out.append(lines.get())
    return "".join(out)


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def descendants(root: int) -> list[int]:
    """Every process below ``root`` (Linux /proc): this sweep's Ray processes, no one else's."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [root]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def running_workers(root: int, title: str, within: float) -> list[int]:
    """The processes below ``root`` whose title starts with ``title``, polled for up to ``within`` s
    (a worker takes its task's title when the task starts)."""
    end = time.monotonic() + within
    while True:
        found = [pid for pid in descendants(root) if cmdline(pid).startswith(title)]
        if found or time.monotonic() > end:
            return found
        time.sleep(0.2)


def run_statuses(out: Path) -> dict[str, str]:
    from mlflow import MlflowClient
    client = MlflowClient(f"sqlite:///{out.resolve() / 'mlflow.db'}")
    exp = client.get_experiment_by_name("debug")
    return {r.info.run_id: r.info.status for r in client.search_runs([exp.experiment_id])}


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_driver_exits_cleanly_and_a_relaunch_resumes(tmp_path, sig):
    out = tmp_path / "sweep"
    proc, lines = start(out)
    wait_for(lines, "round 1/", timeout=300)  # a job is between rounds, with a checkpoint
    sent = time.monotonic()
    proc.send_signal(sig)
    rc = proc.wait(timeout=120)
    stopped_after = time.monotonic() - sent
    text = drain(lines)
    assert rc == 128 + sig, text
    assert f"stopped by {sig.name}" in text and "relaunch the same command to resume" in text
    assert "PC: @" not in text and "Traceback" not in text  # no Ray stack dump, no traceback
    assert stopped_after < 60, f"stopped {stopped_after:.0f} s after the signal"
    statuses = run_statuses(out)
    assert "RUNNING" not in statuses.values() and "KILLED" in statuses.values()
    before = RecordsFile(out).frame
    done_before = set(before.query("kind == 'final' and status == 'FINISHED'")["config_hash"]) \
        if not before.empty else set()
    assert not (out / ".sweep.holder.json").exists()  # released cleanly: no holder note left
    if sig != signal.SIGINT:
        return
    again = subprocess.run([str(BIN / "pipeline-run"), *SWEEP, "executor=ray", "executor.num_cpus=2",
                            "tracking=mlflow", f"output_dir={out}"], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    assert f"{len(done_before)} already finished (skipped)" in again.stdout
    frame = RecordsFile(out).frame.query("kind == 'final'")
    assert len(frame) == 4 and set(frame["status"]) == {"FINISHED"}
    # equal to an uninterrupted sweep of the same jobs
    ref = tmp_path / "reference"
    subprocess.run([str(BIN / "pipeline-run"), *SWEEP, "executor=local", "tracking=none", f"output_dir={ref}"],
                   check=True, capture_output=True, timeout=600)
    cols = ["config_hash", "psnr", "ssim", "selected"]
    ours = frame[cols].sort_values("config_hash").reset_index(drop=True)
    theirs = RecordsFile(ref).frame.query("kind == 'final'")[cols].sort_values("config_hash").reset_index(drop=True)
    assert ours.astype(str).equals(theirs.astype(str))


def test_a_killed_ray_worker_is_retried_from_its_checkpoint(tmp_path):
    """SIGKILL the worker process running a job after its first round: Ray reruns the task, the
    job resumes from its round checkpoint (not from round 0), and the sweep finishes."""
    import os
    out = tmp_path / "sweep"
    # ten rounds, so the job is still running when the driver prints its worker's "round 1/": under a
    # loaded machine Ray's log forwarding lagged past the end of a four-view job (CI, 2026-12-07)
    proc, lines = start(out, "method=[random]", "seeds=[0]", "protocol.budget=12")
    wait_for(lines, "round 1/", timeout=300)
    workers = running_workers(proc.pid, "ray::random:generated", within=30)
    assert workers, "no Ray worker running the job within 30 s of its round 1"
    for pid in workers:
        os.kill(pid, signal.SIGKILL)
    assert proc.wait(timeout=600) == 0, drain(lines)
    frame = RecordsFile(out).frame.query("kind == 'final'")
    assert len(frame) == 1 and frame["status"].iloc[0] == "FINISHED"
    log = next((out / "jobs").glob("*/log.txt")).read_text()
    assert "resuming from the checkpoint after" in log and log.count("round 0:") == 1


def test_a_sigkilled_driver_loses_no_finished_job_and_redoes_none(tmp_path):
    """SIGKILL (no handler runs): the relaunch takes the stale lock over, closes the runs the dead
    driver left RUNNING, skips every job that had finished and completes the rest."""
    out = tmp_path / "sweep"
    proc, lines = start(out, cpus=1)  # one job at a time: some finish, one is cut
    wait_for(lines, "FINISHED", timeout=400)  # at least one job is done
    wait_for(lines, "round 1/", timeout=300)  # and the next one is between rounds
    proc.kill()
    proc.wait(timeout=60)
    frame = RecordsFile(out).frame
    done = set(frame.query("kind == 'final' and status == 'FINISHED'")["config_hash"])
    assert 1 <= len(done) < 4 and (out / ".sweep.holder.json").exists()  # the killed driver's note
    again = subprocess.run([str(BIN / "pipeline-run"), *SWEEP, "executor=ray", "executor.num_cpus=2",
                            "tracking=mlflow", f"output_dir={out}"], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    assert f"{len(done)} already finished (skipped)" in again.stdout
    assert "took over a stale lock" in again.stdout and "left RUNNING by the killed driver" in again.stdout
    final = RecordsFile(out).frame.query("kind == 'final'")
    assert len(final) == 4 and set(final["status"]) == {"FINISHED"}
    assert "RUNNING" not in run_statuses(out).values()


def test_sigint_at_random_moments_of_a_ray_sweep_always_stops_cleanly(tmp_path):
    """The driver spends most of its time inside ``ray.wait``; a handler that raised inside Ray's
    Cython code turned a Ctrl-C into a SystemError traceback and left MLflow runs RUNNING. Three
    signals at seeded random moments after the launch line, wherever the driver happens to be."""
    import random
    delays = random.Random(0).sample([0.3, 1.0, 2.0, 3.5, 5.0, 7.0], 3)
    for trial, delay in enumerate(delays):
        out = tmp_path / f"trial{trial}"
        proc, lines = start(out)
        wait_for(lines, "to run; output in", timeout=300)
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=120)
        text = drain(lines)
        assert rc == 130, f"delay {delay} s: exit {rc}\n{text}"
        assert "Traceback" not in text and "SystemError" not in text, f"delay {delay} s:\n{text}"
        assert "stopped by SIGINT" in text, text
        assert "RUNNING" not in run_statuses(out).values(), f"delay {delay} s"
