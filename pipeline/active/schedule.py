"""How many iterations an episode trains, and when: derived once from the protocol and the config.

The rule (paper Sec. 5, made safe for every budget):

- Round k trains ``epochs_per_view * n_k`` iterations on the n_k views taken so far, then
  evaluates and selects. n_0 = initial views, n_{k+1} = n_k + min(views_per_round, budget - n_k),
  until the budget is reached.
- The final phase trains the last pick in: at least one round's worth with the full budget,
  ``epochs_per_view * budget`` iterations (and at least one), so a post-selection opacity reset is
  never the last thing before an evaluation.
- The total is ``max(fit.iterations, rounds + that minimum)``. When the rounds fit inside
  ``fit.iterations`` (the paper preset: 30k iterations, a view every 100 epochs; Blender at CPU
  scale) nothing changes; otherwise the fit recipe is rescaled to the total, so the
  learning-rate decay, SH-degree steps and densification windows span the iterations actually run.
- ``reload`` (FisherRF's policy) restarts training after every pick, so each round trains from
  scratch and the final phase is a whole fit of ``max(fit.iterations, epochs_per_view * budget)``.
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.fit.config import FitConfig


@dataclass(frozen=True)
class Schedule:
    """round_views [R]: views trained on in each selection round; round_iterations [R]: what each
    round trains before its evaluation; final_iterations: trained after the last pick;
    total: the horizon the fit recipe is scaled to (the final trainer's last step)."""

    round_views: tuple[int, ...]
    round_iterations: tuple[int, ...]
    final_iterations: int
    total: int

    def to_dict(self) -> dict:
        return {"round_views": list(self.round_views), "round_iterations": list(self.round_iterations),
                "final_iterations": self.final_iterations, "total": self.total}


def round_view_counts(initial: int, budget: int, views_per_round: int) -> tuple[int, ...]:
    """Views trained on at each selection round: initial, initial + b, ... while below budget."""
    if initial <= 0 or budget <= initial or views_per_round < 1:
        raise ValueError(f"need 0 < initial ({initial}) < budget ({budget}) and views_per_round "
                         f"({views_per_round}) >= 1")
    counts, n = [], initial
    while n < budget:
        counts.append(n)
        n += min(views_per_round, budget - n)
    return tuple(counts)


def episode_schedule(initial: int, budget: int, views_per_round: int, epochs_per_view: int,
                     fit_iterations: int, reload: bool = False) -> Schedule:
    """The schedule of an episode (see the module docstring for the rule)."""
    views = round_view_counts(initial, budget, views_per_round)
    rounds = tuple(epochs_per_view * n for n in views)
    minimum_final = max(epochs_per_view * budget, 1)
    if reload:
        total = max(fit_iterations, minimum_final)
        return Schedule(views, rounds, total, total)
    total = max(fit_iterations, sum(rounds) + minimum_final)
    return Schedule(views, rounds, total - sum(rounds), total)


@dataclass(frozen=True)
class HeldEvent:
    """A density event of the recipe (``FitConfig.density_events``) at trainer ``step``, in the
    last steps before the evaluation at ``evaluation`` (a round's, or the final one)."""

    step: int
    kind: str  # densify | reset
    evaluation: int


def training_calls(schedule: Schedule, reload: bool = False) -> list[tuple[int, int]]:
    """(first, last) trainer step of each training call of an episode, each ending in an
    evaluation: the rounds', then the final phase. ``reload`` restarts the trainer at step 0
    after every pick (the final phase then trains the whole horizon)."""
    calls, done = [], 0
    for n in schedule.round_iterations:
        first = 1 if reload else done + 1
        calls.append((first, first + n - 1))
        done = 0 if reload else done + n
    calls.append((done + 1, done + schedule.final_iterations))
    return calls


def events_before_evaluations(fit: FitConfig, schedule: Schedule, within: int,
                              reload: bool = False) -> list[HeldEvent]:
    """The density events of ``fit`` (the recipe as run) in the last ``within`` steps of each
    training call: what ``densify_settle=within`` holds, and without it, what an evaluation
    measures before the model has settled."""
    out = []
    for first, last in training_calls(schedule, reload):
        out += [HeldEvent(step, kind, last)
                for step, kind in fit.density_events_between(max(first, last - within + 1), last)]
    return out


def scaled_fit(fit: FitConfig, schedule: Schedule) -> FitConfig:
    """The fit recipe over the schedule's horizon (unchanged when it already is)."""
    return fit if fit.iterations == schedule.total else fit.scaled_to(schedule.total)
