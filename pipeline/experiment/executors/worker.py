"""What every executor runs for one job, on whatever machine it lands.

``run_here`` first refuses to run under other code or other packages than the driver's (the
``DriverIdentity`` it was sent with: a node installed from another commit or another lock computes
other bits under the same config hash), then notes the start in the job folder's ``starts.jsonl``
(one line per start: Ray's retries after a lost node, SLURM's requeues and relaunches all count),
runs the job with its retries and returns the outcome with ``worker``: where and under what it ran
(host, Ray node or SLURM job, pid, code version, packages, CPU, how many starts, when the first began).
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pipeline.data.scene import Scene
from pipeline.experiment.job import Report, run_with_retries
from pipeline.experiment.layout import JobFolder
from pipeline.experiment.outcome import JobOutcome
from pipeline.experiment.provenance import code_version, environment, installed_pins, packages_digest
from pipeline.experiment.spec import Job
from pipeline.splat.compiled import compile_seconds


@dataclass(frozen=True)
class DriverIdentity:
    """The code and packages a worker must run: the driver's (``pins``: name -> version, to say which
    differ; ``prefix``: the driver's environment folder, ``sys.prefix``)."""

    code_version: str
    packages: str
    pins: dict[str, str] = field(default_factory=dict, compare=False)
    prefix: str = ""

    @classmethod
    def here(cls) -> "DriverIdentity":
        """This process's identity, its packages read now (not ``environment()``'s cached digest:
        an install into a shared environment must show)."""
        pins = installed_pins()
        return cls(code_version(), packages_digest(pins), pins, sys.prefix)

    def to_dict(self) -> dict:
        return asdict(self)


def pin_differences(theirs: dict[str, str], ours: dict[str, str], most: int = 5) -> str:
    """'numpy 2.0.0 (driver 1.26.4), scipy missing (driver 1.13.1), ...': what differs, at most ``most``."""
    names = sorted(set(theirs) | set(ours))
    lines = [f"{n} {ours.get(n, 'missing')} (driver {theirs.get(n, 'missing')})" for n in names
             if theirs.get(n) != ours.get(n)]
    return ", ".join(lines[:most]) + (f", and {len(lines) - most} more" if len(lines) > most else "")


def package_advice(expected: DriverIdentity) -> str:
    """What to do about other packages: a node that runs from the driver's own environment folder
    sees an install into it under way (a shared environment), any other needs the lock installed."""
    if expected.prefix and os.path.realpath(expected.prefix) == os.path.realpath(sys.prefix):
        return (f"this node runs from the driver's environment folder ({sys.prefix}): if it is shared, its "
                "packages changed after the launch began (an install into it under way?): let the install "
                "finish and launch again; if it is not shared, install requirements.lock here: make env")
    return "install requirements.lock on every node: make env"


def identity_problem(expected: DriverIdentity | None) -> str | None:
    """Why this process must not run the driver's jobs (None: it may)."""
    if expected is None:
        return None
    here = DriverIdentity.here()
    problems = []
    if here.code_version != expected.code_version:
        problems.append(f"code {here.code_version}, the driver runs {expected.code_version}")
    if here.packages != expected.packages:
        differ = pin_differences(expected.pins, here.pins) if expected.pins else ""
        problems.append(f"packages {here.packages}, the driver's are {expected.packages}"
                        + (f": {differ}" if differ else "") + f" ({package_advice(expected)})")
    if not problems:
        return None
    return f"worker {socket.gethostname()} ({node_name()}) refused: " + "; ".join(problems)


def node_name() -> str:
    """The Ray node id, the SLURM node, or 'local'."""
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        return "ray:" + ray.get_runtime_context().get_node_id()[:12]
    if os.environ.get("SLURM_JOB_ID"):
        return f"slurm:{os.environ.get('SLURMD_NODENAME', '?')}/{os.environ['SLURM_JOB_ID']}"
    if os.environ.get("SUBMITIT_LOCAL_JOB_ID"):
        return f"submitit-local:{os.environ['SUBMITIT_LOCAL_JOB_ID']}"
    return "local"


def record_start(folder: Path) -> list[dict]:
    """Append this start to ``starts.jsonl``; every start so far (this one last)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = JobFolder(folder).starts_file
    line = {"host": socket.gethostname(), "node": node_name(), "pid": os.getpid(), "started": time.time()}
    with open(path, "a") as f:
        f.write(json.dumps(line) + "\n")
    return read_starts(folder)


def read_starts(folder: Path) -> list[dict]:
    path = JobFolder(folder).starts_file
    if not path.exists():
        return []
    out = []
    for text in path.read_text().splitlines():
        try:
            out.append(json.loads(text))
        except json.JSONDecodeError:  # a line cut short by a killed node
            continue
    return out


def run_here(job: Job, scene: Scene | None = None, report: Report | None = None,
             expected: DriverIdentity | None = None) -> JobOutcome:
    """Run ``job`` in this process (its retries included); never raises for an application error."""
    if job.execution is None:
        raise ValueError(f"{job.label}: a job without its execution settings cannot run")
    folder = Path(job.execution.job_dir)
    starts = record_start(folder)
    problem = identity_problem(expected)
    compiling = compile_seconds()
    if problem is not None:
        outcome = JobOutcome.failed(1, [problem])
    else:
        outcome = run_with_retries(job, scene, report)
    env = environment()
    outcome.worker = {"host": starts[-1]["host"], "node": starts[-1]["node"], "pid": os.getpid(),
                      "code_version": code_version(), "packages": env.packages, "locked": env.locked,
                      "cpu": env.cpu, "numerics": env.numerics, "starts": len(starts), "first_started": starts[0]["started"],
                      "ended": time.time(), "compile_seconds": round(compile_seconds() - compiling, 3)}
    return outcome
