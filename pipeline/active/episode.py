"""One active-reconstruction episode: (scene, strategy, protocol, seed) -> records.

initial views -> train -> select from the remaining pool -> add -> post-selection policy -> ...
until the budget -> final training -> evaluation. How long each phase trains is the
``pipeline.active.schedule`` rule: the final phase always trains the last pick in, and the fit
recipe spans the iterations actually run. A final model that scores more than ``DEGRADED_DB``
below the last round on the same views is flagged ``degraded`` in the final metrics.
``run_episode`` is a pure function of its inputs: it returns records and calls an optional
per-round callback, it never logs or tracks. With a checkpoint folder it saves its state after
every round and resumes from the last finished one, ending with the same result as an
uninterrupted run.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Callable

import torch

from pipeline.acquisition import POSE_SCORING, SelectionContext, make_strategy, scores_any_pose
from pipeline.acquisition.validation import RoundAsk, check_selection
from pipeline.active.checkpoint import fingerprint, load_checkpoint, save_checkpoint
from pipeline.active.config import EpisodeConfig
from pipeline.active.pose_selection import AcquiredViews, episode_pose_space, make_world, search_next_pose
from pipeline.interchange.results import EpisodeResult, FinalMetrics, RoundRecord
from pipeline.active.plan import EpisodePlan
from pipeline.cameras import Cameras
from pipeline.splat.compiled import compile_seconds
from pipeline.data.protocols import ProtocolViews
from pipeline.data.images import read_mask
from pipeline.data.sampling import reduce_pool, seeded_subset
from pipeline.data.scene import Scene
from pipeline.eval.metrics import LpipsMetric, evaluate_views
from pipeline.fit.init import from_point_cloud, random_in_box
from pipeline.fit.trainer import Trainer
from pipeline.memory import peak_rss_mb
from pipeline.splat import Gaussians, ply
from pipeline.splat.gaussians import num_sh_bases

# A final PSNR this far below the last round's, on the same curve views, flags the episode.
DEGRADED_DB = 3.0


def initial_gaussians(scene: Scene, cfg: EpisodeConfig) -> Gaussians:
    """``init="ply:PATH"``: the Gaussians of a 3DGS PLY (SH padded with zeros or cut to the fit's
    degree); else SfM points when the scene has them (a seeded subset of at most ``init_points``),
    else a random cloud in the scene box."""
    fit = cfg.fit
    if cfg.init is not None:
        return with_sh_degree(ply.load(cfg.init[len("ply:"):]), fit.sh_degree)
    if scene.points is not None and len(scene.points):
        gen = torch.Generator().manual_seed(cfg.seed)
        keep = seeded_subset(list(range(len(scene.points))), min(fit.init_points, len(scene.points)), gen)
        return from_point_cloud(scene.points[keep].float(), scene.point_colors[keep].float(),
                                fit.sh_degree, fit.init_opacity)
    lo, hi = scene.bounds()
    return random_in_box(fit.init_points, lo.float(), hi.float(), fit.sh_degree, cfg.seed, fit.init_opacity)


def with_sh_degree(g: Gaussians, degree: int) -> Gaussians:
    """``g`` with exactly the SH coefficients of ``degree``: extra ones dropped, missing ones zero."""
    if degree <= g.sh_degree:
        return g.at_sh_degree(degree)
    pad = g.shN.new_zeros(len(g), num_sh_bases(degree) - 1 - g.shN.shape[1], 3)
    return g.replace(shN=torch.cat([g.shN, pad], dim=1))


class Episode:
    """The mutable state of one episode between rounds (what a checkpoint holds)."""

    def __init__(self, scene: Scene, cfg: EpisodeConfig, device: str | torch.device | None = None,
                 folder: Path | None = None, plan: EpisodePlan | None = None):
        self.scene, self.cfg, self.folder = scene, cfg, folder
        self.plan = plan if plan is not None else EpisodePlan.of(scene, cfg)
        self.on_step = None  # hears each training step (run_episode's on_step)
        self.on_fisher = None  # hears (views done, views asked) of each Fisher pass of a selection
        self.device = torch.device(device or "cpu")
        self.background = scene.background.to(self.device)
        self.views: ProtocolViews = self.plan.views
        self.pool = scene.split(self.views.pool_split)
        self.test = scene.split(self.views.test_split)
        if cfg.masks and scene.masks is None:
            raise ValueError(f"masks=true but scene {scene.root} was read without masks "
                             "(load_scene(..., masks=True) reads a capture's masks/)")
        if cfg.fit.image_width is not None and self.pool.cameras.width != cfg.fit.image_width:
            raise ValueError(f"scene {scene.root} was read at width {self.pool.cameras.width} but "
                             f"fit.image_width is {cfg.fit.image_width}")
        self.schedule, self.fit = self.plan.schedule, self.plan.fit
        self.strategy = make_strategy(cfg.strategy, **cfg.strategy_options)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.curve_ids = list(self.plan.curve_ids)
        self.init = initial_gaussians(scene, cfg).to(self.device)
        self.extent = self.plan.extent
        self.taken = list(self.views.initial_ids)
        self.acquired = AcquiredViews(first_id=len(self.pool.cameras))  # views captured off the pool
        self.world, self.space = None, None
        if cfg.world != "dataset":
            if not scores_any_pose(self.strategy):
                raise ValueError(f"world={cfg.world}: strategy {cfg.strategy!r} cannot score a pose off the pool "
                                 f"(a pose search needs a strategy that scores any camera: {', '.join(POSE_SCORING)})")
            self.world = make_world(scene, cfg)
            self.space = episode_pose_space(scene, self.views, cfg.protocol)
        self.records: list[RoundRecord] = []
        self.trainer = self._new_trainer()
        self.done = False
        self.final: FinalMetrics | None = None

    def images(self, split, ids: list[int]) -> torch.Tensor:
        return split.images.stack(ids).to(self.device)  # [len(ids), H, W, 3]

    def taken_cameras(self) -> Cameras:
        """The cameras of the taken views, in order (pool views and captured ones)."""
        if not any(self.acquired.is_acquired(v) for v in self.taken):
            return self.pool.cameras[self.taken]
        return Cameras.cat([self.acquired.camera(v) if self.acquired.is_acquired(v) else self.pool.cameras[[v]]
                            for v in self.taken])

    def masks(self, split_name: str, ids: list[int]) -> torch.Tensor | None:
        """[len(ids), H, W] masks of a split's views when the episode uses masks (else None); a
        view captured off the pool has none (all ones)."""
        if not self.cfg.masks:
            return None
        split = self.scene.split(split_name)
        size = (split.cameras.width, split.cameras.height)
        files = self.scene.masks[split_name]
        return torch.stack([torch.ones(size[1], size[0]) if i >= len(files) else read_mask(files[i], size)
                            for i in ids]).to(self.device)

    def taken_masks(self) -> torch.Tensor | None:
        return self.masks(self.views.pool_split, self.taken)

    def taken_images(self) -> torch.Tensor:
        """[len(taken), H, W, 3] in taken order."""
        if not any(self.acquired.is_acquired(v) for v in self.taken):
            return self.images(self.pool, self.taken)
        return torch.stack([self.acquired.image(v).to(self.device) if self.acquired.is_acquired(v)
                            else self.images(self.pool, [v])[0] for v in self.taken])

    def _new_trainer(self) -> Trainer:
        fit = self.fit
        if self.cfg.post_selection == "reset_opacity":
            # the paper resets opacities after every selection instead of on 3DGS's fixed schedule;
            # both would put resets right before an evaluation of the PSNR-vs-views curve
            fit = fit.with_changes(densify=replace(fit.densify, periodic_opacity_reset=False))
        return Trainer(self.init, self.taken_cameras(), self.taken_images(),
                       fit, self.background, extent=self.extent, nonfinite_dir=self.folder,
                       masks=self.taken_masks())

    # -- checkpoint ---------------------------------------------------------------------------
    def state(self, key: str) -> dict:
        return {"fingerprint": key, "taken": self.taken, "records": [asdict(r) for r in self.records],
                "trainer": self.trainer.state_dict(), "generator": self.generator.get_state(),
                "torch_rng": torch.get_rng_state(), "done": self.done,
                "final": self.final.to_dict() if self.final is not None else None,
                "acquired": self.acquired.state()}

    def restore(self, state: dict) -> None:
        self.taken = list(state["taken"])
        self.records = [RoundRecord.from_dict(r) for r in state["records"]]
        self.acquired.restore(state.get("acquired", {"poses": []}))
        self.trainer.set_views(self.taken_cameras(), self.taken_images(), self.taken_masks())
        self.trainer.load_state_dict(state["trainer"])
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        self.done = state["done"]
        self.final = FinalMetrics.from_dict(state["final"]) if state["final"] else None

    # -- steps --------------------------------------------------------------------------------
    def train(self, iterations: int, progress: bool) -> float:
        start = time.perf_counter()
        self.trainer.train(max(iterations, 0), progress=progress,
                           desc=f"{self.cfg.strategy} {len(self.taken)} views", on_step=self.on_step,
                           settle=self.cfg.densify_settle or 0)
        return time.perf_counter() - start

    def evaluate_curve(self) -> dict:
        """The mean psnr, ssim, ssim_skimage of the curve's test views."""
        return evaluate_views(self.trainer.rendered_gaussians, self.test.cameras[self.curve_ids],
                              self.images(self.test, self.curve_ids), self.background,
                              masks=self.masks(self.views.test_split, self.curve_ids)).mean()

    def record(self, train_seconds: float) -> RoundRecord:
        m = self.evaluate_curve()
        return RoundRecord(len(self.records), len(self.taken), self.trainer.step, m["psnr"], m["ssim"],
                           len(self.trainer.rendered_gaussians), round(train_seconds, 3),
                           test_ssim_skimage=m["ssim_skimage"])

    def draw_probes(self, round_index: int) -> list[int]:
        return self.plan.probes(self.cfg.seed, round_index)

    def goal_manifold(self) -> dict | None:
        """The protocol's target manifold (its up axis filled in), None when the goal is the scene."""
        p = self.cfg.protocol
        data = p.manifold if p.kind == "goal" else p.probe_manifold
        return None if data is None else {"up": list(self.views.up), **data}

    def select(self, rec: RoundRecord) -> None:
        rec.probes = self.draw_probes(rec.round)
        taken = set(self.taken)
        remaining = [i for i in self.views.pool_ids if i not in taken]
        if self.cfg.pool_keep_fraction < 1:
            remaining = reduce_pool(remaining, self.cfg.pool_keep_fraction, self.generator)
        count = min(self.cfg.views_per_round, self.views.budget - len(self.taken), len(remaining))
        ctx = SelectionContext(self.trainer.rendered_gaussians, self.pool.cameras[remaining], remaining,
                               self.taken_cameras(), self.background, self.generator,
                               self.pool.cameras[rec.probes], self.taken_images(),
                               self.trainer.settings, taken_ids=list(self.taken), probe_ids=list(rec.probes),
                               goal_manifold=self.goal_manifold(), on_fisher=self.on_fisher)
        cpu, compiling = time.process_time(), compile_seconds()
        sel = self.strategy.select(ctx, count)
        check_selection(RoundAsk(self.cfg.strategy, rec.round, count, tuple(remaining), tuple(self.taken)),
                        list(sel.chosen), dict(sel.scores))
        rec.selected, rec.candidates = [int(c) for c in sel.chosen], len(remaining)
        rec.scores = {int(k): float(v) for k, v in sel.scores.items()}
        search_seconds = self.search_pose(ctx, rec) if self.world is not None else 0.0
        compiled = compile_seconds() - compiling  # one-time: kept apart from the selection's cost
        rec.compile_seconds = round(compiled, 3)
        rec.selection_cpu_seconds = round(max(0.0, time.process_time() - cpu - compiled), 3)
        rec.per_candidate_ms = round(max(0.0, sel.seconds_per_candidate - compiled / max(len(remaining), 1)) * 1e3, 3)
        rec.selection_seconds = round(max(0.0, sel.round_seconds + search_seconds - compiled), 3)
        rec.fisher_seconds = round(sel.fisher_seconds, 3)
        rec.peak_rss_mb = round(max(sel.peak_rss_mb, peak_rss_mb()), 1)
        self.taken += rec.selected

    def search_pose(self, ctx: SelectionContext, rec: RoundRecord) -> float:
        """Off the pool (world != dataset): search the strategy's score over the pose space from
        the pool's best candidates and random poses. The searched pose is captured by the
        simulator and replaces the pool pick in ``rec.selected`` when it scores better than the
        pool's best candidate (whose exact camera need not lie on the pose space's shell); else
        the pool pick stands (the pose space extends the pool, it never loses a candidate).
        ``rec.search`` says which (``taken``: search | pool | pool_captured, the last when the
        pool pick's image is the simulator's, ``search.capture_pool_picks``); the pool's scores
        stay in ``rec.scores``. With ``search.evaluations`` 0 nothing is searched. Returns the seconds."""
        start = time.perf_counter()
        options = self.cfg.search_options()
        if options["evaluations"] == 0:
            rec.search = {"score": None, "best_start_score": None, "best_pool_score": None, "evaluations": 0,
                          "seconds": 0.0, "taken": "pool", "evaluated": []}
        else:
            self._search(ctx, rec)
        if rec.search["taken"] == "pool" and options["capture_pool_picks"]:
            self._capture_pool_pick(rec)
        return time.perf_counter() - start

    def _search(self, ctx: SelectionContext, rec: RoundRecord) -> None:
        scorer = self.strategy.pose_scorer(ctx)
        pool_costs = scorer.pool_costs(rec.scores)
        choice = search_next_pose(scorer, ctx, pool_costs, self.space, self.cfg, rec.round)
        best_pool = min(pool_costs.values())
        rec.search = {"score": choice.score, "best_start_score": choice.best_start_score,
                      "best_pool_score": best_pool, "evaluations": choice.evaluations,
                      "seconds": choice.seconds, "taken": "pool",
                      "evaluated": choice.evaluated}  # the score landscape the search saw
        if choice.score < best_pool - 1e-9 * abs(best_pool):  # the same pose again is no gain
            image = self.world.capture(choice.camera).to(self.device)
            rec.selected = [self.acquired.add(choice.pose, choice.camera, image)]
            rec.poses = [list(choice.pose)]
            rec.search["taken"] = "search"

    def _capture_pool_pick(self, rec: RoundRecord) -> None:
        """The pool pick's camera, its image rendered by the simulator (its pose recorded as the
        pose space's coordinates of the camera, which need not lie on its shell)."""
        camera = self.pool.cameras[rec.selected]
        pose = self.space.poses_of(camera)[0].tolist()
        image = self.world.capture(camera).to(self.device)
        rec.selected = [self.acquired.add(pose, camera, image)]
        rec.poses = [pose]
        rec.search["taken"] = "pool_captured"

    def after_selection(self) -> None:
        policy = self.cfg.post_selection
        if policy == "reload":
            skipped = self.trainer.nonfinite_steps  # the count spans the whole episode
            self.trainer = self._new_trainer()
            self.trainer.nonfinite_steps = skipped
            return
        self.trainer.set_views(self.taken_cameras(), self.taken_images(), self.taken_masks())
        if policy == "reset_opacity" and self.recovers_from_a_reset():
            self.trainer.reset_opacity()

    def next_round_iterations(self) -> int:
        """What the round after the current pick trains before its evaluation."""
        upcoming = len(self.records) + 1  # after_selection runs before the current round is recorded
        rounds = self.schedule.round_iterations
        return rounds[upcoming] if upcoming < len(rounds) else self.schedule.final_iterations

    def recovers_from_a_reset(self) -> bool:
        """``reset_recovery``: reset only when the next round trains at least that many steps."""
        need = self.cfg.reset_recovery
        return need is None or self.next_round_iterations() >= need

    def fingerprint_data(self) -> dict:
        """What a checkpoint must match: the config and, when the rule rescaled it, the fit's
        horizon (a checkpoint of an older schedule is then refused rather than mixed in)."""
        data = {"scene": str(self.scene.root), "config": self.cfg.to_dict()}
        if self.fit.iterations != self.cfg.fit.iterations:
            data["fit_iterations"] = self.fit.iterations
        return data

    def finish(self, progress: bool) -> None:
        iterations = max(self.schedule.total - self.trainer.step, 1)
        seconds = self.train(iterations, progress)
        last_round = self.records[-1] if self.records else None
        rec = self.record(seconds)
        rec.peak_rss_mb = round(peak_rss_mb(), 1)
        self.records.append(rec)
        drop = last_round.test_psnr - rec.test_psnr if last_round is not None else 0.0
        lpips = LpipsMetric() if self.cfg.lpips else None
        m = evaluate_views(self.trainer.rendered_gaussians, self.test.cameras[self.views.test_ids],
                           self.images(self.test, self.views.test_ids), self.background, lpips,
                           masks=self.masks(self.views.test_split, self.views.test_ids))
        mean = m.mean()
        self.final = FinalMetrics(
            mean["psnr"], mean["ssim"], mean["ssim_skimage"], mean["lpips"],
            m.lpips_status if lpips else "LPIPS disabled in the config", len(self.views.test_ids),
            m.psnr, m.ssim, m.ssim_skimage, len(self.trainer.rendered_gaussians),
            iterations=self.trainer.step, final_phase_iterations=iterations,
            schedule=self.schedule.to_dict(), curve_psnr_drop=round(drop, 3),
            degraded=bool(drop > DEGRADED_DB), nonfinite_steps=self.trainer.nonfinite_steps)
        self.done = True


def run_episode(scene: Scene, cfg: EpisodeConfig, checkpoint_dir: str | Path | None = None,
                on_round: Callable[[RoundRecord], None] | None = None,
                progress: bool = False, device: str | torch.device | None = None,
                on_selection: Callable[["Episode", RoundRecord], None] | None = None,
                on_resume: Callable[[int], None] | None = None,
                on_step: Callable[..., None] | None = None, plan: EpisodePlan | None = None) -> EpisodeResult:
    """Run (or resume) one episode. ``on_round`` sees each finished round's record (after it is
    checkpointed), including the final one; it may raise to stop the episode. ``device``: where
    the model and images live (default CPU); records are identical in form on every device.
    ``on_selection(episode, record)`` sees the episode after each pick, before the post-selection
    policy changes the model (it must not change the episode). ``on_resume(rounds)`` hears how many
    finished rounds a checkpoint restored. ``on_step(round, done, total, phase)`` hears every training
    step of a round (``phase`` "training"; ``round`` counts from 0; the final training is the last
    round) and, with ``phase`` "fisher", every chunk of views of a selection's Fisher passes.
    ``plan``: the episode's plan when the caller has made it (``EpisodePlan.of(scene, cfg)``)."""
    start = time.perf_counter()
    folder = Path(checkpoint_dir) if checkpoint_dir is not None else None
    ep = Episode(scene, cfg, device, folder, plan)
    if on_step is not None:
        ep.on_step = lambda done, total, info: on_step(len(ep.records), done, total, "training")
        ep.on_fisher = lambda done, total: on_step(len(ep.records), done, total, "fisher")
    key = fingerprint(ep.fingerprint_data())
    state = load_checkpoint(folder, key)
    if state is not None:
        ep.restore(state)
        if on_resume is not None:
            on_resume(len(ep.records))
    while not ep.done and len(ep.taken) < ep.views.budget:
        seconds = ep.train(cfg.epochs_per_view * len(ep.taken), progress)
        rec = ep.record(seconds)
        ep.select(rec)
        if on_selection is not None:  # the model that made this round's pick (e.g. round images)
            on_selection(ep, rec)
        ep.after_selection()
        ep.records.append(rec)
        _checkpoint(ep, folder, key, on_round, rec)
    if not ep.done:
        ep.finish(progress)
        _checkpoint(ep, folder, key, on_round, ep.records[-1])
    return EpisodeResult(str(scene.root), cfg.strategy, cfg.seed, cfg.protocol.kind,
                         list(ep.views.initial_ids), ep.taken[len(ep.views.initial_ids):],
                         [r.probes for r in ep.records[:-1]], ep.views.pool_split, ep.views.test_split,
                         list(ep.views.test_ids), ep.curve_ids, ep.records, ep.final,
                         round(time.perf_counter() - start, 2), ep.trainer.rendered_gaussians,
                         acquired_poses=ep.acquired.poses if cfg.world != "dataset" else None,
                         acquired_cameras=ep.acquired.cameras)


def _checkpoint(ep: Episode, folder: Path | None, key: str, on_round, rec: RoundRecord) -> None:
    if folder is not None:
        save_checkpoint(folder, ep.state(key))
    if on_round is not None:
        on_round(rec)
