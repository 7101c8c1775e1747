"""The trainer's Adam against torch.optim.Adam(fused=True), its oracle: the same parameters and
moments bit for bit, step by step and through the density control's remaps and opacity reset; the
state_dict each writes loads into the other; and a process that trains never imports TorchDynamo."""

import subprocess
import sys

import pytest
import torch

from pipeline.fit.adam import FusedAdam
from pipeline.fit.densify import remap, reset_opacity

NAMES = ("means", "log_scales", "logit_opacities")
RATES = {"means": 1.6e-4, "log_scales": 5e-3, "logit_opacities": 5e-2}


def _params(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    shapes = {"means": (n, 3), "log_scales": (n, 3), "logit_opacities": (n,)}
    return {k: torch.randn(shapes[k], generator=gen).requires_grad_(True) for k in NAMES}


def _groups(params):
    return [{"params": [params[k]], "lr": RATES[k], "name": k} for k in NAMES]


def _grads(params, gen):
    for p in params.values():
        p.grad = torch.randn(p.shape, generator=gen) * 10.0 ** torch.randint(-6, 2, (), generator=gen).item()


def _same(a: dict, b: dict, opt_a, opt_b):
    for k in NAMES:
        assert torch.equal(a[k], b[k]), k
        sa, sb = opt_a.state[a[k]], opt_b.state[b[k]]
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(sa[key], sb[key]) and sa[key].dtype == sb[key].dtype, (k, key)


def test_every_step_and_remap_is_torchs_fused_adam_bit_for_bit():
    ours, theirs = _params(50), _params(50)
    mine = FusedAdam(_groups(ours), eps=1e-15)
    oracle = torch.optim.Adam(_groups(theirs), eps=1e-15, fused=True)
    gen_a, gen_b = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    for step in range(1, 41):
        _grads(ours, gen_a)
        _grads(theirs, gen_b)
        if step % 7 == 0:  # a group without a gradient is skipped, its moments untouched
            ours["log_scales"].grad = theirs["log_scales"].grad = None
        mine.step()
        oracle.step()
        _same(ours, theirs, mine, oracle)
        if step == 10:  # the density control: rows kept, rows appended with zero moments
            keep = torch.arange(50) % 3 != 0
            new = {k: torch.ones(4, *ours[k].shape[1:]) for k in NAMES}
            ours, theirs = remap(ours, mine, keep, new), remap(theirs, oracle, keep, new)
            _same(ours, theirs, mine, oracle)
        if step == 20:
            ours, theirs = reset_opacity(ours, mine, 0.01), reset_opacity(theirs, oracle, 0.01)
            _same(ours, theirs, mine, oracle)
        for group in mine.param_groups + oracle.param_groups:  # the means' schedule
            if group["name"] == "means":
                group["lr"] *= 0.97


def test_a_state_dict_of_either_loads_into_the_other():
    ours, theirs = _params(20), _params(20)
    mine = FusedAdam(_groups(ours), eps=1e-15)
    oracle = torch.optim.Adam(_groups(theirs), eps=1e-15, fused=True)
    gen_a, gen_b = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    for _ in range(3):
        _grads(ours, gen_a)
        _grads(theirs, gen_b)
        mine.step()
        oracle.step()
    for group in oracle.param_groups + mine.param_groups:
        group["lr"] = 0.5 if group["name"] == "means" else group["lr"]
    written = mine.state_dict()
    assert written.keys() == oracle.state_dict().keys()
    assert written["param_groups"] == oracle.state_dict()["param_groups"]  # torch's layout, key for key
    into_torch = torch.optim.Adam(_groups(_params(20)), eps=1e-15, fused=True)
    into_torch.load_state_dict(written)
    into_ours = FusedAdam(_groups(_params(20)), eps=1e-15)
    into_ours.load_state_dict(oracle.state_dict())
    for loaded, source in ((into_torch, mine), (into_ours, oracle)):
        assert [g["lr"] for g in loaded.param_groups] == [g["lr"] for g in source.param_groups]
        for lg, sg in zip(loaded.param_groups, source.param_groups):
            a, b = loaded.state[lg["params"][0]], source.state[sg["params"][0]]
            assert all(torch.equal(a[key], b[key]) for key in ("step", "exp_avg", "exp_avg_sq"))
    with pytest.raises(ValueError, match="'log_scales' where 'means' was expected"):
        wrong = FusedAdam(_groups(_params(20)), eps=1e-15)
        saved = mine.state_dict()
        saved["param_groups"][0]["name"] = "log_scales"
        wrong.load_state_dict(saved)


def test_a_process_that_trains_never_imports_torchdynamo():
    """torch.optim's wrappers import torch._dynamo (3.5 s, 71 MB) on first use; a process that fits,
    densifies and checkpoints through the trainer does not."""
    probe = subprocess.run([sys.executable, "-c", TRAIN_AND_CHECKPOINT], capture_output=True, text=True, timeout=600)
    assert probe.returncode == 0, probe.stderr[-3000:]
    assert probe.stdout.strip().splitlines()[-1] == "dynamo imported: False", probe.stdout[-2000:]


TRAIN_AND_CHECKPOINT = """
import sys
import torch
from pipeline.fit.config import DensifyConfig, FitConfig
from pipeline.fit.trainer import Trainer
from pipeline.splat import render
from pipeline.splat.scenes import random_scene, sphere_cameras
cams = sphere_cameras(3, 24, 24)
truth = random_scene(200, seed=1)
images = torch.stack([render(truth, cams[i]).rgb[0] for i in range(3)])
config = FitConfig(iterations=40, sh_degree=1, image_width=24, init_points=100,
                   densify=DensifyConfig(start=5, stop=30, interval=10, max_gaussians=400))
trainer = Trainer(random_scene(100, seed=2), cams, images, config)
trainer.train(20)
trainer.reset_opacity()
state = trainer.state_dict()
trainer.load_state_dict(state)
trainer.train(20)
print("dynamo imported:", "torch._dynamo" in sys.modules)
"""
