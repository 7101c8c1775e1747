"""Beyond the pool: how a sweep's pose searches went, read from its records.

A method searched off the pool when its round rows carry ``search_taken`` (``search``: the searched
pose beat the pool's best candidate and was captured; ``pool``: the pool pick stood;
``pool_captured``: the pool pick, its image the simulator's, the control). Costs are the
strategy's score as a search minimises it (``PoseScorer``: GO-PRE's score, FisherRF's and POp-GS's
gains negated). Three things come out of a sweep:

- per method and setting, how often the search won, by how much (relative to the pool's best
  cost) and what it cost (selection time per round beside every other method's);
- each searched method against its pool twin (the method of the same strategy that never
  searched, e.g. ``fisherrf_search`` against ``fisherrf``) and against the capture control when the
  sweep has one (the pool picks with the simulator's images, ``gopre_pool_captured``), paired over seeds;
- the score landscape each round's search saw (``rec.search.evaluated``, read from the job's
  ``result.json``): azimuth x elevation coloured by cost, the starts, the pose found, the pool's best.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.interchange.sweep_results import SweepResults
from pipeline.report.rows import finished
from pipeline.report.stats import paired_comparisons, with_curve_area
from pipeline.report.tables import PairedTable


def search_rounds(frame: pd.DataFrame) -> pd.DataFrame:
    """The finished round rows of episodes that searched off the pool (empty when none did)."""
    if "search_taken" not in frame:
        return frame.iloc[:0]
    rounds = finished(frame, "round")
    return rounds[rounds["search_taken"].notna()]


WORLD_NOTES = {
    "generated": "Views off the pool are the generated scene's exact images (its analytic ray caster).",
    "twin": "Views off the pool are renders of the scene's digital twin (a splat trained on all of its "
            "training views), not photographs; every PSNR is on the dataset's real held-out test views.",
}


def world_notes(frame: pd.DataFrame) -> list[str]:
    """What a view captured off the pool is, for each capture simulator the searched methods used."""
    rounds = search_rounds(frame)
    worlds = dict.fromkeys(rounds["world"].dropna()) if "world" in rounds else {}
    return [WORLD_NOTES[w] for w in worlds if w in WORLD_NOTES]


def searched_methods(frame: pd.DataFrame) -> list[str]:
    return list(dict.fromkeys(search_rounds(frame)["method"]))


def _setting(frame: pd.DataFrame) -> pd.Series:
    return frame["setting"].fillna("") if "setting" in frame else pd.Series("", index=frame.index)


def search_table(frame: pd.DataFrame) -> str:
    """Markdown: per scene, setting and searched method, the rounds, the share whose searched pose
    was captured and the mean relative cost gain over the pool's best in those rounds."""
    rounds = search_rounds(frame)
    rounds = rounds.assign(setting=_setting(rounds))
    lines = ["| scene | setting | method | episodes | rounds | searched pose captured | "
             "cost below the pool's best (captured rounds, mean) | pool pick rendered by the simulator |",
             "|---|---|---|---|---|---|---|---|"]
    for (scene, setting, method), part in rounds.groupby(["scene", "setting", "method"], sort=False):
        taken = part[part["search_taken"] == "search"]
        gain = ((taken["search_best_pool_score"] - taken["search_score"])
                / taken["search_best_pool_score"].abs()).mean()
        share = f"{len(taken)} ({len(taken) / len(part):.0%})"
        rendered = int((part["search_taken"] == "pool_captured").sum())
        lines.append(f"| {scene} | {setting} | {method} | {part['config_hash'].nunique()} | {len(part)} | "
                     f"{share} | {'—' if taken.empty else f'{gain:.2%}'} | {rendered} |")
    return "\n".join(lines) + "\n"


def selection_time_table(frame: pd.DataFrame) -> str:
    """Markdown: selection time per round of every method (the search's included), per scene and
    setting, mean over episodes: the cost a win off the pool must be stated against."""
    final = finished(frame, "final")
    final = final.assign(setting=_setting(final))
    lines = ["| scene | setting | method | selection CPU s / round | selection wall s / round |",
             "|---|---|---|---|---|"]
    for (scene, setting, method), part in final.groupby(["scene", "setting", "method"], sort=False):
        cpu = pd.to_numeric(part.get("selection_cpu_seconds"), errors="coerce").mean()
        wall = pd.to_numeric(part.get("selection_seconds"), errors="coerce").mean()
        lines.append(f"| {scene} | {setting} | {method} | {_num(cpu)} | {_num(wall)} |")
    return "\n".join(lines) + "\n"


def _num(value: float) -> str:
    return "—" if value is None or value != value else f"{value:.2f}"


def pool_twin(frame: pd.DataFrame, method: str) -> str | None:
    """The method of the same strategy that never searched, when there is exactly one."""
    final = frame[frame["kind"] == "final"]
    strategy = set(final.loc[final["method"] == method, "strategy"])
    searched = set(searched_methods(frame))
    twins = [m for m in dict.fromkeys(final["method"])
             if m not in searched and set(final.loc[final["method"] == m, "strategy"]) == strategy]
    return twins[0] if len(twins) == 1 else None


def capture_control(frame: pd.DataFrame, method: str) -> str | None:
    """The method of the same strategy whose every round took the pool pick rendered by the
    simulator (``pool_captured``: e.g. gopre_pool_captured), when there is exactly one: against it
    a searched method's gain is the searched poses' alone, without the simulator's images."""
    rounds = search_rounds(frame)
    final = frame[frame["kind"] == "final"]
    strategy = set(final.loc[final["method"] == method, "strategy"])
    controls = [m for m, part in rounds.groupby("method", sort=False)
                if m != method and (part["search_taken"] == "pool_captured").all()
                and set(final.loc[final["method"] == m, "strategy"]) == strategy]
    return controls[0] if len(controls) == 1 else None


def twin_tables(frame: pd.DataFrame, title: str, skip: str | None = None) -> list[PairedTable]:
    """Per setting and pool twin, the searched methods of its strategy against it (final PSNR and
    the curve area), paired over scenes and seeds; none against ``skip`` (the report's own
    reference, whose paired tables already have those rows)."""
    final = finished(frame, "final")
    final = with_curve_area(final, finished(frame, "round")).assign(setting=lambda f: _setting(f))
    references = {m: (pool_twin(frame, m), capture_control(frame, m)) for m in searched_methods(frame)}
    controls = {control for _, control in references.values()} - {None}
    groups: dict[str, list[str]] = {}
    for method, pair in references.items():
        for reference in pair:
            if reference is not None and reference != skip:
                groups.setdefault(reference, []).append(method)
    out = []
    for setting in dict.fromkeys(final["setting"]):
        part = final[final["setting"] == setting]
        for twin, methods in groups.items():
            rows: dict[str, dict] = {}
            for metric in ("psnr", "psnr_auc"):
                sub = part[part["method"].isin([twin, *methods])]
                if twin not in set(sub["method"]):
                    continue
                for c in paired_comparisons(sub, twin, metric, methods):
                    rows.setdefault(c.method, {})[metric] = c
            if rows:
                label = f", {setting}" if setting else ""
                against = (f"the pool picks with the simulator's images ({twin})" if twin in controls
                           else f"the pool ({twin})")
                out.append(PairedTable(f"{title}{label}: searched off the pool against {against}",
                                       twin, ["psnr", "psnr_auc"], rows))
    return out


@dataclass
class RoundLandscape:
    """What one round's search evaluated: poses [E, 3] (azimuth, elevation in degrees, radius),
    their costs [E], the pose of least cost [3], the pool's best cost and which pick was taken."""

    round: int
    poses: np.ndarray
    costs: np.ndarray
    best: np.ndarray
    best_pool_cost: float
    taken: str

    def relative_costs(self) -> np.ndarray:
        """(cost - the pool's best) / |the pool's best| [E]: below zero beats every pool candidate."""
        return (self.costs - self.best_pool_cost) / abs(self.best_pool_cost)


def landscapes(result: dict) -> list[RoundLandscape]:
    """The rounds of a job's ``result.json`` that searched, as landscapes."""
    out = []
    for rec in result.get("rounds", []):
        search = rec.get("search")
        if not search or not search.get("evaluated"):
            continue
        evaluated = np.asarray(search["evaluated"], dtype=float)  # [E, 4]
        best = evaluated[int(np.argmin(evaluated[:, 3]))]
        out.append(RoundLandscape(int(rec["round"]), evaluated[:, :3], evaluated[:, 3], best[:3],
                                  float(search["best_pool_score"]), str(search["taken"])))
    return out


def landscape_jobs(frame: pd.DataFrame, sweep_dir: Path) -> dict[str, list[RoundLandscape]]:
    """For each scene, setting and searched method: its first seed's searched rounds (label -> landscapes)."""
    rounds = search_rounds(frame)
    rounds = rounds.assign(setting=_setting(rounds))
    results, out = SweepResults(sweep_dir), {}
    for (scene, setting, method), part in rounds.groupby(["scene", "setting", "method"], sort=False):
        first = part.sort_values("seed").iloc[0]
        episode = results.episode_data(str(first["config_hash"]))
        if episode is not None:
            label = ", ".join(x for x in (method, scene, setting, f"seed {first['seed']}") if x)
            out[label] = landscapes(episode)
    return out
