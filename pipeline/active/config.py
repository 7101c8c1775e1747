"""What one episode runs: the fit recipe, the schedule, the post-selection policy, evaluation.

The schedule follows the paper: with n views taken, train ``epochs_per_view`` passes over them
(``epochs_per_view * n`` iterations), select, add; once the budget is reached, train the last pick
in: up to ``max(fit.iterations, rounds + epochs_per_view * budget)`` in all, the fit recipe rescaled
to that total when the rounds alone would not fit (``pipeline.active.schedule`` states the rule).
Post-selection policies:

- ``reset_opacity`` (the paper, default): clamp every opacity to the reset value, continue.
- ``reload`` (FisherRF): restart from the initial Gaussians with fresh optimizer and schedules.
- ``continue``: just keep training.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from pipeline.bounds import BOOL, FLOAT, INT, STR, bounded, require_bounds
from pipeline.data.protocols import ProtocolConfig
from pipeline.fit.config import DensifyConfig, FitConfig, paper_preset

POLICIES = ("reset_opacity", "reload", "continue")
# where a view's image comes from: the dataset's pool (every strategy), or a capture simulator that
# renders any pose (pipeline.world): the pick is then a pose searched in the pose space
WORLDS = ("dataset", "generated", "twin")
# evaluations 0: no search (the pool pick); capture_pool_picks: a pool pick's image is the simulator's
# render of its camera, not the dataset's photo (with evaluations 0, the control for a simulator's images)
SEARCH_KEYS = {"evaluations": 60, "pool_starts": 3, "random_starts": 3, "seconds": None,
               "capture_pool_picks": False}


@dataclass(frozen=True)
class EpisodeConfig:
    fit: FitConfig = field(default_factory=paper_preset)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    strategy: str = "gopre"
    strategy_options: dict = field(default_factory=dict)
    epochs_per_view: int = bounded(100, INT, ge=1, usual_max=10_000)  # E: one view every E passes over the
    # taken views (0 would evaluate a just-reset model)
    views_per_round: int = bounded(1, INT, ge=1)           # greedy batch size b
    pool_keep_fraction: float = bounded(1.0, FLOAT, gt=0, le=1)  # candidate-pool reduction (keep a
    # seeded fraction per round)
    post_selection: str = bounded("reset_opacity", STR, choices=POLICIES)
    curve_test_views: int | None = bounded(None, INT, ge=1, nullable=True)  # test views for the per-round
    # curve (None: all)
    lpips: bool = bounded(True, BOOL)                      # try LPIPS at the final evaluation
    seed: int = bounded(0, INT, ge=0)
    init: str | None = None             # "ply:PATH": start from a 3DGS PLY instead of points/box
    world: str = bounded("dataset", STR, choices=WORLDS)   # see WORLDS
    world_model: str | None = None      # twin: "ply:PATH" of the reference splat
    search: dict = field(default_factory=dict)  # pose search (world != dataset): SEARCH_KEYS
    masks: bool = bounded(False, BOOL)  # train and evaluate on the capture's masked-in pixels only
    # reset_opacity only: a round that trains fewer iterations than this after its pick keeps the
    # opacities (a reset needs that many steps to recover before the round's evaluation); None:
    # reset after every pick (the paper)
    reset_recovery: int | None = bounded(None, INT, ge=1, nullable=True)
    # no density event (densification, prune, periodic opacity reset) in the last this many steps
    # before each evaluation (every round's and the final one), so what is measured has settled;
    # None: the recipe's events wherever they fall (3DGS, the paper)
    densify_settle: int | None = bounded(None, INT, ge=1, nullable=True)

    def __post_init__(self) -> None:
        require_bounds(self)  # each declared field; the relations between fields below
        budget, initial = self.protocol.budget, self.protocol.initial_views
        if budget is not None and self.views_per_round > budget - (initial or 1):
            raise ValueError(f"views_per_round: {self.views_per_round} is more than the picks the budget "
                             f"leaves (protocol.budget={budget}, initial views {initial or 'the default'})")
        if self.init is not None and not (isinstance(self.init, str) and self.init.startswith("ply:")
                                          and len(self.init) > 4):
            raise ValueError(f"init must be 'ply:PATH' or null, got {self.init!r}")
        self._check_world()

    def _check_world(self) -> None:
        if (self.world == "twin") != (self.world_model is not None):
            raise ValueError("world_model ('ply:PATH' of the reference splat) is set with world=twin and only then, "
                             f"got world={self.world!r}, world_model={self.world_model!r}")
        if self.world_model is not None and not (isinstance(self.world_model, str)
                                                 and self.world_model.startswith("ply:")):
            raise ValueError(f"world_model must be 'ply:PATH', got {self.world_model!r}")
        unknown = set(self.search) - set(SEARCH_KEYS)
        if unknown:
            raise ValueError(f"search: unknown keys {sorted(unknown)}; allowed {sorted(SEARCH_KEYS)}")
        if self.search and self.world == "dataset":
            raise ValueError("search: the pose search needs a capture simulator (world=generated or twin)")
        if self.world != "dataset" and self.views_per_round != 1:
            raise ValueError(f"views_per_round must be 1 with world={self.world} (one searched pose per round)")
        options = self.search_options()
        if not (isinstance(options["evaluations"], int) and options["evaluations"] >= 0):
            raise ValueError(f"search.evaluations must be an integer >= 0 (0: no search), "
                             f"got {options['evaluations']!r}")
        for key in ("pool_starts", "random_starts"):
            if not (isinstance(options[key], int) and options[key] >= 0):
                raise ValueError(f"search.{key} must be an integer >= 0, got {options[key]!r}")
        if options["evaluations"] and options["pool_starts"] + options["random_starts"] < 1:
            raise ValueError("search: needs at least one start (pool_starts + random_starts >= 1)")
        if not isinstance(options["capture_pool_picks"], bool):
            raise ValueError(f"search.capture_pool_picks must be true or false, got {options['capture_pool_picks']!r}")

    def search_options(self) -> dict:
        """The pose search's options, defaults filled in."""
        return {**SEARCH_KEYS, **self.search}

    def with_changes(self, **changes) -> "EpisodeConfig":
        return replace(self, **changes)

    def to_dict(self) -> dict:
        """Plain data (checkpoint fingerprints); ``init`` only when set and the world's fields
        only off the dataset, so checkpoints written before the options existed still match."""
        out = asdict(self)
        if out["init"] is None:
            del out["init"]
        if not out["masks"]:  # a checkpoint of an unmasked episode matches as before
            del out["masks"]
        for optional in ("reset_recovery", "densify_settle"):  # so does one of the paper's rules
            if out[optional] is None:
                del out[optional]
        if self.world == "dataset":  # so are the world's fields (they matter only beyond the pool)
            for key in ("world", "world_model", "search"):
                del out[key]
        return out


def round_seed(seed: int, round_index: int) -> int:
    """The seed of a round's own random draws (its goal probes, a pose search), from the episode's
    seed and the round: independent of what was picked before (paper Sec. 5)."""
    return seed * 100_003 + round_index


def paper_episode(**changes) -> EpisodeConfig:
    """The paper's scale: 30k iterations at full resolution, a view every 100 epochs."""
    return replace(EpisodeConfig(fit=paper_preset(), epochs_per_view=100), **changes)


def cpu_episode(**changes) -> EpisodeConfig:
    """2 CPU cores: 64 px, 2000 iterations in all, a view every 25 epochs, <= 10k Gaussians,
    the per-round curve on 50 test views (the final metrics use every test view).

    Schedules keep 3DGS's proportions of its 30k run: densify over the first half, an opacity
    reset and the start of big-Gaussian pruning every tenth of the run, the SH degree raised every
    1/30 of it (every number below is 3DGS's scaled by 2000 / 30k, rounded). Until the fidelity
    fixes the reset interval was a third of the run, so the big-Gaussian prune switched on
    mid-episode and removed a quarter of a real scene's Gaussians at once.
    3DGS's world-size prune (max scale > 0.1 x extent) is off: with <= 10k Gaussians, 100x fewer
    than 3DGS, a real scene's background is covered by Gaussians above that size, and the rule
    removed ~15% of them at once whenever it switched on (bonsai: -3.7 dB in one round, measured;
    reports/fidelity.md). The screen-size prune (20 px) stays, from a tenth of the run on.
    A real scene's longer episode (4 -> 20 views) rescales this recipe (``pipeline.active.schedule``).
    ``conf/splat/cpu.yaml`` lists every value (a test keeps the two equal).
    """
    fit = FitConfig(iterations=2000, sh_degree=3, sh_degree_interval=67, image_width=64, init_points=5000,
                    densify=DensifyConfig(start=100, stop=1000, interval=67, prune_large_after=200,
                                          opacity_reset_interval=200, max_world_scale=None,
                                          max_gaussians=10_000))
    return replace(EpisodeConfig(fit=fit, epochs_per_view=25, curve_test_views=50), **changes)


def tiny_episode(**changes) -> EpisodeConfig:
    """Tests and smoke runs: 32 px, 240 iterations, a 4-view budget, SH degree 1, no opacity reset
    or big-Gaussian prune within the run (``conf/splat/tiny.yaml`` lists every value)."""
    fit = FitConfig(iterations=240, sh_degree=1, sh_degree_interval=80, image_width=32, init_points=600,
                    densify=DensifyConfig(start=48, stop=160, interval=32, prune_large_after=8000,
                                          opacity_reset_interval=8000, max_gaussians=5000))
    protocol = ProtocolConfig(initial_views=2, budget=4, probes=4)
    return replace(EpisodeConfig(fit=fit, protocol=protocol, epochs_per_view=20, curve_test_views=8,
                                 lpips=False), **changes)


EPISODE_PRESETS = {"paper": paper_episode, "cpu": cpu_episode, "tiny": tiny_episode}


def episode_preset(name: str, **changes) -> EpisodeConfig:
    if name not in EPISODE_PRESETS:
        raise ValueError(f"unknown episode preset {name!r}; choose one of {sorted(EPISODE_PRESETS)}")
    return EPISODE_PRESETS[name](**changes)
