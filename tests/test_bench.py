"""The benchmark commands run and print one JSON record per backend (their figures are measured
by hand on an idle machine, never asserted here)."""

import json

from pipeline.bench import train
from pipeline.splat import compiled


def test_bench_train_interleaves_its_backends_and_prints_one_record_each(capsys, monkeypatch):
    order = []
    real_step = train.Trainer.train_step

    def step(self):
        order.append(compiled.fused_enabled())  # which variant ran this step
        return real_step(self)

    monkeypatch.setattr(train.Trainer, "train_step", step)
    train.main(["--size", "16", "--gaussians", "150", "--steps", "2", "--repeats", "2",
                "--backends", "compiled-unfused", "compiled"])
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["backend"] for r in rows] == ["compiled-unfused", "compiled"]
    assert all(r["its_per_s"] > 0 and r["steps"] == 2 and r["repeats"] == 2 for r in rows)
    # 5 warm-up steps each, then blocks of 2 alternating: unfused, fused, unfused, fused
    assert order == [False] * 5 + [True] * 5 + [False, False, True, True] * 2
