"""``pipeline-run ... plan=true``: the job table of a sweep, what is already finished, and an
estimated duration from the recorded durations of finished jobs of the same kind. Starts nothing:
no Ray, no MLflow, no job folders.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pipeline.experiment.records import RecordsFile
from pipeline.experiment.spec import Job


@dataclass
class PlannedJob:
    job: Job
    finished: bool
    estimate_s: float | None  # from finished jobs of the same kind; None when there are none


def _durations(records: pd.DataFrame) -> pd.DataFrame:
    if records.empty or "wall_seconds" not in records:
        return pd.DataFrame(columns=["dataset", "scene", "method", "setting", "wall_seconds"])
    final = records[(records["kind"] == "final") & (records["status"] == "FINISHED")]
    if "job_compile_seconds" in final:  # one-time compilation out (absent in older records)
        compiled = pd.to_numeric(final["job_compile_seconds"], errors="coerce").fillna(0.0)
        final = final.assign(wall_seconds=final["wall_seconds"] - compiled)
    return final[["dataset", "scene", "method", "setting", "wall_seconds"]].dropna(subset=["wall_seconds"])


def estimate(job: Job, durations: pd.DataFrame) -> float | None:
    """Median wall time of finished jobs of the same kind (without the one-time kernel compilation
    a fresh machine's first jobs paid: ``job_compile_seconds``): same dataset, scene, method and
    setting (any seed); else the same dataset and method; else None."""
    for keys in (("dataset", "scene", "method", "setting"), ("dataset", "method")):
        same = durations
        for k in keys:
            same = same[same[k].fillna("") == (getattr(job, k) or "")]
        if not same.empty:
            return float(same["wall_seconds"].median())
    return None


def hyperparameter_text(jobs: list[Job]) -> str:
    """Every hyperparameter the jobs' episodes run with, once per distinct set (the fit recipe
    after the preset, splat.iterations / image_width / max_gaussians and any splat.fit.* overrides,
    then the episode's own settings), with the jobs (methods) that use it."""

    groups: dict[str, list[str]] = {}
    for job in jobs:
        cfg = job.episode
        values = {**{f"fit.{k}": v for k, v in cfg.fit.flat().items() if k != "seed"},
                  **{k: getattr(cfg, k) for k in ("epochs_per_view", "views_per_round", "pool_keep_fraction",
                                                  "post_selection", "curve_test_views", "lpips")}}
        text = "\n".join(f"  {k} = {v}" for k, v in values.items())
        groups.setdefault(text, []).append(f"{job.method} on {job.scene}")
    out = []
    for text, users in groups.items():
        names = sorted(set(users))
        out += [f"hyperparameters of {', '.join(names[:4])}{' ...' if len(names) > 4 else ''} "
                f"(override any with splat.fit.<name>=value, conf/splat/ lists them; fit.iterations through splat.iterations; an "
                f"episode whose rounds need more iterations rescales the recipe, pipeline/active/schedule.py):",
                text]
    return "\n".join(out)


def plan_jobs(jobs: list[Job], output_dir: Path) -> list[PlannedJob]:
    records = RecordsFile(output_dir)
    done = records.finished_hashes()
    durations = _durations(records.frame)
    return [PlannedJob(j, j.config_hash in done, estimate(j, durations)) for j in jobs]


def slots(executor: dict, jobs: list[Job]) -> int:
    """Jobs that run at once: the local executor 1; Ray the CPUs it gets over the job threads."""
    if executor.get("kind") != "ray" or not jobs:
        return 1
    cpus = executor.get("num_cpus") or os.cpu_count() or 1
    return max(1, int(cpus) // max(1, min(int(j.execution.threads) for j in jobs)))


def format_duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def plan_text(name: str, planned: list[PlannedJob], parallel: int, warnings: list[str] = ()) -> str:
    """The job table, then ``warnings`` (allowed values far above anything measured), then the
    summary with the estimate."""
    header = ["#", "dataset", "scene", "method", "seed", "axes", "config hash", "status", "estimate"]
    rows = []
    for p in planned:
        j = p.job
        est = "-" if p.finished else (format_duration(p.estimate_s) if p.estimate_s is not None else "unknown")
        rows.append([str(j.index), j.dataset, j.scene, j.method, str(j.seed),
                     j.setting or "-", j.config_hash, "finished" if p.finished else "to run", est])
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in [header] + rows]
    todo = [p for p in planned if not p.finished]
    known = [p.estimate_s for p in todo if p.estimate_s is not None]
    summary = f"[{name}] plan: {len(planned)} jobs, {len(planned) - len(todo)} finished, {len(todo)} to run"
    if todo and known:
        total = sum(known) / len(known) * len(todo)  # unknown ones counted at the known mean
        summary += (f"; about {format_duration(total / parallel)} on {parallel} parallel slot(s) "
                    f"({len(known)} of {len(todo)} estimated from finished jobs of the same kind)")
    elif todo:
        summary += "; no finished job of the same kind to estimate the duration from"
    notes = [f"warning: {w}" for w in warnings]
    return "\n".join(lines + [""] + notes + [summary, "nothing was started (plan=true)"])
