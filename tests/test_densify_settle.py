"""``densify_settle``: no density event (densification, prune, periodic opacity reset) in the last
N steps before an evaluation. The trainer holds exactly the events a brute force over the recipe
finds there, ``events_before_evaluations`` lists the same ones (what ``plan=true`` prints), the
held densification's statistics carry into the next one, and an episode passes the setting to
every training call of its rounds and its final phase."""

import random

import pytest
import torch

import pipeline.fit.trainer as trainer_module
from pipeline.active import run_episode, tiny_episode
from pipeline.active.schedule import episode_schedule, events_before_evaluations, training_calls
from pipeline.data.load import load_scene
from pipeline.data.synthetic import generate
from pipeline.fit import Trainer
from pipeline.fit.config import DensifyConfig, FitConfig
from pipeline.splat import render
from pipeline.splat.scenes import random_scene, sphere_cameras

# densify every 5 steps in (5, 60), a periodic reset every 15 steps before 60 and not in the last
# tenth of the 60 steps (so 15, 30, 45; not 60)
RECIPE = FitConfig(iterations=60, sh_degree=0, image_width=16, init_points=50,
                   densify=DensifyConfig(start=5, stop=60, interval=5, opacity_reset_interval=15,
                                         prune_large_after=1000, max_gaussians=500))


def by_hand_events(step: int) -> list[str]:
    """The recipe's events at ``step``, written out from 3DGS's rule for RECIPE's numbers."""
    out = []
    if 5 < step < 60 and step % 5 == 0:
        out.append("densify")
    if step < 60 and step % 15 == 0 and step <= 54:
        out.append("reset")
    return out


def recording_trainer(monkeypatch) -> tuple[Trainer, list[tuple[int, str]]]:
    """A trainer on RECIPE whose densifications and resets are recorded as (step, kind)."""
    seen = []
    real_densify = trainer_module.densify_and_prune

    def densify(params, optimizer, stats, *args):
        seen.append((trainer.step, "densify", float(stats.count.max())))
        return real_densify(params, optimizer, stats, *args)

    real_reset = Trainer.reset_opacity
    monkeypatch.setattr(trainer_module, "densify_and_prune", densify)
    monkeypatch.setattr(Trainer, "reset_opacity", lambda self, value=None: (seen.append((self.step, "reset", 0.0)),
                                                                            real_reset(self, value)))
    g = random_scene(50, seed=0)
    cams = sphere_cameras(3, 16, 16)
    with torch.no_grad():
        images = render(g, cams).rgb
    trainer = Trainer(g, cams, images, RECIPE)
    return trainer, seen


@pytest.mark.parametrize("settle", [0, 1, 4, 7])
def test_the_trainer_holds_exactly_the_events_in_the_last_settle_steps_of_each_call(monkeypatch, settle):
    trainer, seen = recording_trainer(monkeypatch)
    calls = [13, 17, 30]  # ends at 13, 30, 60
    expected, first = [], 1
    for n in calls:
        last = first + n - 1
        expected += [(s, kind) for s in range(first, last + 1) if s <= last - settle for kind in by_hand_events(s)]
        first = last + 1
    for n in calls:
        trainer.train(n, settle=settle)
    assert [(s, k) for s, k, _ in seen] == expected
    if settle == 0:  # nothing held: the recipe's events, all of them
        assert len(expected) == len([1 for s in range(1, 61) for _ in by_hand_events(s)]) == 13
    assert trainer._settle_from is None  # a later call without settle is not held


def test_a_held_densification_leaves_its_statistics_to_the_next_one(monkeypatch):
    """With settle 7 the densifications at 10 (the first call ends at 13), 25 and 30 (the second
    ends at 30) are held: the one at 15 sees the statistics of steps 1-15 and the one at 35 those
    of steps 21-35 (a Gaussian seen at every step counts each: the count's maximum)."""
    trainer, seen = recording_trainer(monkeypatch)
    for n in (13, 17, 30):
        trainer.train(n, settle=7)
    counts = {s: c for s, k, c in seen if k == "densify"}
    assert sorted(counts) == [15, 20, 35, 40, 45, 50]
    assert counts[20] == 5 and counts[40] == 5  # the usual interval
    assert counts[15] == 15 and counts[35] == 15


def test_events_before_evaluations_lists_what_the_trainer_holds(monkeypatch):
    """The listing ``plan=true`` prints is the set the trainer leaves out, on random schedules."""
    rng = random.Random(0)
    for _ in range(20):
        rounds = [rng.randint(3, 15) for _ in range(rng.randint(1, 4))]
        settle = rng.randint(1, 8)
        total = sum(rounds) + rng.randint(1, 60 - sum(rounds)) if sum(rounds) < 59 else 60
        final = total - sum(rounds)
        from pipeline.active.schedule import Schedule
        schedule = Schedule(tuple(range(1, len(rounds) + 1)), tuple(rounds), final, total)
        listed = {(e.step, e.kind) for e in events_before_evaluations(RECIPE, schedule, settle)}
        for e in events_before_evaluations(RECIPE, schedule, settle):
            assert 0 <= e.evaluation - e.step < settle
        trainer, seen = recording_trainer(monkeypatch)
        for n in (*rounds, final):
            trainer.train(n, settle=settle)
        done = {(s, k) for s, k, _ in seen}
        everything = {(s, k) for s in range(1, total + 1) for k in by_hand_events(s)}
        assert done | listed == everything and not done & listed
        monkeypatch.undo()


def test_density_events_between_are_the_events_the_rule_names_in_any_window():
    """The enumeration ``events_before_evaluations`` uses (multiples of the two intervals) against
    every step of the window asked one by one, on random recipes: starts, stops and intervals
    that do not divide each other, windows from step 0 on, the reset on and off."""
    rng = random.Random(1)
    for _ in range(300):
        densify = DensifyConfig(start=rng.randint(0, 50), stop=rng.randint(1, 400), interval=rng.randint(1, 40),
                                opacity_reset_interval=rng.randint(1, 90),
                                periodic_opacity_reset=rng.random() < 0.8)
        fit = FitConfig(iterations=rng.randint(50, 500), densify=densify)
        first = rng.randint(0, 300)
        last = first + rng.randint(0, 200)
        assert fit.density_events_between(first, last) == \
            [(s, kind) for s in range(max(first, 1), last + 1) for kind in fit.density_events(s)], \
            (fit.densify, first, last)


def test_training_calls_tile_the_horizon_and_reload_restarts_each():
    s = episode_schedule(4, 8, 1, 25, 2000)
    calls = training_calls(s)
    assert calls[0][0] == 1 and calls[-1][1] == s.total
    assert all(b[0] == a[1] + 1 for a, b in zip(calls, calls[1:]))
    assert [b - a + 1 for a, b in calls] == [*s.round_iterations, s.final_iterations]
    r = episode_schedule(4, 8, 1, 25, 2000, reload=True)
    assert training_calls(r, reload=True) == [(1, n) for n in r.round_iterations] + [(1, r.total)]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("gen") / "scene", seed=0, size=32, n_train=14, n_test=8)


def test_an_episode_holds_the_densification_just_before_its_evaluation(scene_dir, monkeypatch):
    """tiny: rounds of 40 and 60 steps (evaluations at 40 and 100), then 140 to 240; densify at
    64, 96, 128. ``densify_settle=10`` holds the one at 96, 4 steps before the evaluation at 100."""
    steps = []
    real = trainer_module.densify_and_prune
    monkeypatch.setattr(trainer_module, "densify_and_prune",
                        lambda *args: (steps.append(len(steps)), real(*args))[1])
    seen = []
    real_train = Trainer.train
    monkeypatch.setattr(Trainer, "train", lambda self, n, *a, **k: (seen.append((self.step, n, k.get("settle"))),
                                                                   real_train(self, n, *a, **k))[1])
    for settle, expected in ((None, 3), (10, 2)):
        steps.clear(), seen.clear()
        cfg = tiny_episode(strategy="coverage", densify_settle=settle)
        run_episode(load_scene(scene_dir, width=cfg.fit.image_width), cfg)
        assert len(steps) == expected
        assert seen == [(0, 40, settle or 0), (40, 60, settle or 0), (100, 140, settle or 0)]
    with pytest.raises(ValueError, match="densify_settle: 0 is not an integer >= 1, or null"):
        tiny_episode(densify_settle=0)
