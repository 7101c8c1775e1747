"""``gopre-run ... plan=true``: the job table of a sweep, what is already finished, and an
estimated duration from the recorded durations of finished jobs of the same kind. Starts nothing:
no Ray, no MLflow, no job folders.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pipeline.active.config import EpisodeConfig
from pipeline.active.plan import EpisodeOutline
from pipeline.active.schedule import Schedule, events_before_evaluations, training_calls
from pipeline.data.scene import traits_of
from pipeline.experiment.data_changes import data_changes
from pipeline.experiment.executors.config import planned_slots
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.schema import EPISODE_SETTINGS
from pipeline.experiment.spec import Job
from pipeline.fit.config import FitConfig


@dataclass
class PlannedJob:
    job: Job
    finished: bool
    estimate_s: float | None  # from finished jobs of the same kind; None when there are none
    data_change: str | None = None  # the scene's data changed since its job finished here (the line that says so)


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
                  **{k: getattr(cfg, k) for k in EPISODE_SETTINGS}}
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


def held_line(cfg: EpisodeConfig, run: FitConfig, schedule: Schedule) -> str:
    """The density events close before an evaluation: those ``densify_settle`` holds, or without
    it those less than a densification interval before one (which it could hold)."""
    reload = cfg.post_selection == "reload"
    settle = cfg.densify_settle
    events = events_before_evaluations(run, schedule, settle or run.densify.interval, reload)
    listed = ", ".join(f"{e.kind} at {e.step} ({e.evaluation - e.step} before the evaluation at {e.evaluation})"
                       for e in events) or "none"
    if settle:
        return f"  densify_settle={settle} holds these density events: {listed}"
    return (f"  density events less than a densification interval ({run.densify.interval} steps) before an "
            f"evaluation (+splat.densify_settle=N holds those in the last N steps): {listed}")


def density_line(run: FitConfig, schedule: Schedule, reload: bool) -> str:
    """How many density events the recipe as run has over the episode's training calls, and at
    which steps the first and last fall; says plainly when there are none (density control off:
    the model keeps the Gaussians it starts with)."""
    events = [(e.step, e.kind) for e in events_before_evaluations(run, schedule, schedule.total, reload)]
    # (a window as long as the episode: every event of every training call)
    if not events:
        return ("  density control: none in the episode (no densification, prune or periodic opacity "
                "reset: the model keeps the Gaussians it starts with)")
    parts = []
    for kind, name in (("densify", "densifications"), ("reset", "periodic opacity resets")):
        steps = [step for step, k in events if k == kind]
        parts.append(f"{len(steps)} {name} (steps {min(steps)} to {max(steps)})" if steps else f"no {name}")
    return f"  density control: {', '.join(parts)}"


def schedule_lines(job: Job, outline: EpisodeOutline) -> list[str]:
    """An episode's schedule in words, then each recipe value the schedule's rescaling changes
    (as written -> as run)."""
    cfg = job.episode
    reload = cfg.post_selection == "reload"
    schedule, written, run = outline.schedule, cfg.fit, outline.fit
    views = schedule.round_views
    head = f"{len(views)} rounds ({views[0]} to {views[-1]} views, {cfg.views_per_round} picked a round)"
    lines = [f"  {head}: the rounds train {', '.join(map(str, schedule.round_iterations))} steps"
             f"{' (each from scratch: post_selection=reload)' if reload else ''}, evaluating at step "
             f"{', '.join(str(last) for _, last in training_calls(schedule, reload)[:-1])}; then "
             f"{schedule.final_iterations} after the last pick"]
    lines.append(density_line(run, schedule, reload))
    lines.append(held_line(cfg, run, schedule))
    if run is written:
        lines.append(f"  {schedule.total} steps in all: the recipe runs as written")
        return lines
    lines.append(f"  {schedule.total} steps in all, so the recipe of {written.iterations} runs rescaled "
                 f"x{schedule.total / written.iterations:.2f}, a value set with splat.fit.* with it "
                 f"(as written -> as run):")
    before, after = written.flat(), run.flat()
    lines += [f"    fit.{k} = {before[k]} -> {after[k]}" for k in before if k != "seed" and before[k] != after[k]]
    return lines


def schedule_text(jobs: list[Job]) -> str:
    """What the episode jobs run, once per distinct schedule with the jobs that follow it: each
    round's training steps and the step of its evaluation, the density events close before an
    evaluation, and the fit recipe after an episode longer than the recipe rescales it
    (``pipeline.active.schedule``), which ``hyperparameter_text`` shows as written. From the
    config and the scene's format alone: the same before a generated scene exists."""
    groups: dict[str, list[str]] = {}
    for job in jobs:
        if job.kind == "episode":
            text = "\n".join(schedule_lines(job, EpisodeOutline.before_reading(traits_of(job.format), job.episode)))
            groups.setdefault(text, []).append(f"{job.method} on {job.scene}")
    out = []
    for text, users in groups.items():
        names = sorted(set(users))
        out += [f"schedule of {', '.join(names[:4])}{' ...' if len(names) > 4 else ''} "
                f"(pipeline/active/schedule.py):", text]
    return "\n".join(out)


def plan_jobs(jobs: list[Job], output_dir: Path) -> list[PlannedJob]:
    records = RecordsFile(output_dir)
    done = records.finished_hashes()
    durations = _durations(records.frame)
    changed = {(c.dataset, c.scene): c.line() for c in data_changes(jobs, records.frame)}
    return [PlannedJob(j, j.config_hash in done, estimate(j, durations), changed.get((j.dataset, j.scene)))
            for j in jobs]


def slots(executor: dict, jobs: list[Job]) -> int:
    """Jobs that run at once, as the executor's section says (``executors.config``)."""
    return planned_slots(executor, [int(j.execution.threads) for j in jobs if j.execution is not None])


def format_duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def plan_text(name: str, planned: list[PlannedJob], parallel: int, warnings: tuple[str, ...] | list[str] = ()) -> str:
    """The job table, then ``warnings`` (allowed values far above anything measured), then the
    summary with the estimate."""
    header = ["#", "dataset", "scene", "method", "seed", "axes", "config hash", "status", "estimate"]
    rows = []
    for p in planned:
        j = p.job
        est = "-" if p.finished else (format_duration(p.estimate_s) if p.estimate_s is not None else "unknown")
        rows.append([str(j.index), j.dataset, j.scene, j.method, str(j.seed),
                     j.setting or "-", j.config_hash,
                     "finished" if p.finished else "to run (data changed)" if p.data_change else "to run", est])
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
    notes += sorted({p.data_change for p in planned if p.data_change and not p.finished})
    return "\n".join(lines + [""] + notes + [summary, "nothing was started (plan=true)"])
