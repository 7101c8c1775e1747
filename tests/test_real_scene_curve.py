"""On a real capture at ``splat=cpu`` the PSNR-vs-views curve does not collapse mid-episode.

Before the fidelity fixes (issue 26) every method's bonsai curve fell 3-6 dB between 11 and 12
views: 3DGS's world-size prune of big Gaussians switched on at iteration 1,701 (the opacity-reset
interval of the rescaled recipe) and removed about a quarter of the Gaussians at once. The episode
runs to its 13-view round, past both that old switch and the new one (a tenth of the run).
"""

import pytest

from conftest import shared_scene
from pipeline.active import run_episode
from pipeline.active.config import cpu_episode
from pipeline.data.load import load_scene
from pipeline.data.protocols import ProtocolConfig

pytestmark = pytest.mark.slow


class Enough(Exception):
    pass


def test_no_round_of_a_bonsai_episode_falls_more_than_1_db_below_the_previous():
    cfg = cpu_episode(strategy="random", protocol=ProtocolConfig(kind="global"), lpips=False)
    scene = load_scene(shared_scene("colmap", "bonsai"), width=cfg.fit.image_width)
    rounds = []

    def on_round(rec):
        rounds.append(rec)
        if rec.num_views >= 13:
            raise Enough
    with pytest.raises(Enough):
        run_episode(scene, cfg, on_round=on_round)
    assert rounds[-1].iteration > 1710  # past the old switch (densification at 1,710 of 5,100)
    psnr = [r.test_psnr for r in rounds]
    drops = [(r.num_views, a - b) for r, a, b in zip(rounds[1:], psnr, psnr[1:])]
    assert max(d for _, d in drops) < 1.0, f"curve drops (views, dB): {drops}"
