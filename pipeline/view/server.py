"""The viewer: one episode in a viser scene, its rounds replayed, and a goal the user draws.

Scene: the trained splat; every pool and test camera as a frustum coloured by its role at the
shown round (initial, selected with its pick order, this round's pick, probe, test, remaining
candidate coloured by its score's rank); the protocol's target sector; the drawn goal's sector.
GUI: a round slider; the goal (sector start, width, direction, or picked pool views; K probes)
and a "Score next view" button that runs the sweeps' GO-PRE strategy on the shown round's model;
a camera chooser (or a click on a frustum) showing that view's ground truth, render and
per-pixel predictive variance.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.data.manifolds import SectorManifold
from pipeline.data.protocols import resolved_manifold
from pipeline.eval.images import colormap, to_uint8
from pipeline.fisher.exact import predictive_variance_maps
from pipeline.fisher.variance import POSTERIOR_LAMBDA, taken_views_posterior
from pipeline.splat import render
from pipeline.view.geometry import (ROLE_COLOURS, camera_poses, lower_is_better, score_ranks,
                                    sector_outline, splat_arrays, standing_colour, vertical_fov)
from pipeline.view.goal import GoalScores, gopre_options, pool_ids, score_goal
from pipeline.view.run import EpisodeRun, RoundState

DIRECTIONS = ("clockwise", "counter-clockwise")
LEGEND = ("**Colours**: initial views **blue** · selected **green** (labelled #k in pick order) · "
          "this round's pick / the goal's next best view **red** · probes **purple** · test views "
          "**grey** (smaller) · remaining candidates from **dark teal** (worst score) to **bright "
          "cyan** (best) · the protocol's target sector **orange**, a drawn goal's sector **red** · "
          "off the pool (world=generated | twin): captured views in the same colours (their captions "
          "say so), the poses the round's search evaluated as points from **dark teal** (worst "
          "score) to **bright cyan** (best)")
GOAL_KINDS = ("sector", "picked cameras")


@dataclass(frozen=True)
class CameraKey:
    split: str                   # "pool", "test" or "captured" (views captured off the pool)
    index: int                   # view id in that split

    @property
    def label(self) -> str:
        return f"{self.split} {self.index}"


def enlarged(image: np.ndarray, width: int = 256) -> np.ndarray:
    """Nearest-neighbour upscaling by a whole factor, so a 64-pixel image shows its pixels."""
    factor = max(1, width // image.shape[1])
    return image.repeat(factor, axis=0).repeat(factor, axis=1)


def camera_roles(run: EpisodeRun, state: RoundState, goal: GoalScores | None) -> dict[int, tuple[str, str]]:
    """Role and caption of every pool view at ``state``: initial, selected #k (taken before this
    round), picked (this round's pick, or the drawn goal's next best view), probe, candidate; and
    of every view captured off the pool (ids after the pool's): selected, picked, or later."""
    roles: dict[int, tuple[str, str]] = {}
    order = {view: k + 1 for k, view in enumerate(run.selected)}
    probes = goal.probes if goal is not None else state.probes
    picked = [goal.best] if goal is not None else state.picked
    for a in range(len(run.captured) if run.captured is not None else 0):  # captured off the pool
        view = run.first_captured + a
        if view in state.taken:
            roles[view] = ("selected", f"selected #{order[view]}, captured off the pool")
        elif view in picked:
            roles[view] = ("picked", f"picked this round (#{order.get(view, '?')}), captured off the pool")
        else:
            roles[view] = ("later", "captured in a later round")
    for view in pool_ids(run):
        if view in run.initial:
            roles[view] = ("initial", "initial view")
        elif view in state.taken:
            roles[view] = ("selected", f"selected #{order[view]}")
        elif view in picked:
            roles[view] = ("picked", "next best view" if goal is not None else
                           f"picked this round (#{order.get(view, '?')})")
        elif view in probes:
            roles[view] = ("probe", "probe of the goal" if goal is not None else "probe of this round")
        else:
            roles[view] = ("candidate", "candidate")
    return roles


def key_of_view(run: EpisodeRun, view: int) -> CameraKey:
    """The frustum key of a pool or captured view id."""
    if run.is_captured(view):
        return CameraKey("captured", view - run.first_captured)
    return CameraKey("pool", view)


class EpisodeViewer:
    """Builds the scene and GUI for ``run`` on ``server`` (every browser tab shares them) or, with
    ``client``, on that one client only (its own goal, round and camera: ``per_client_viewers``);
    every handle it updates is kept."""

    def __init__(self, run: EpisodeRun, server, start_round: int | None = None, client=None):
        self.run, self.server, self.client = run, server, client
        target = client if client is not None else server
        self.scene, self.gui = target.scene, target.gui
        self.lock = threading.Lock()
        self.goal: GoalScores | None = None
        self.variances: dict[int, torch.Tensor] = {}
        self.frustums: dict[CameraKey, object] = {}
        self.labels: dict[int, object] = {}
        self.shown: CameraKey | None = None   # the camera the panel shows
        self.goal_sector = None              # the drawn goal's outline, while its scores stand
        self.landscape = None                # the round's searched poses (off-pool runs)
        rounds = len(run.rounds)
        if rounds == 0:
            raise ValueError(f"{run.folder}: the episode has no finished selection round to show")
        self.state = run.round_state(rounds - 1 if start_round is None else min(start_round, rounds - 1))
        up = np.asarray(run.views.up, dtype=np.float64)
        self.scene.set_up_direction(tuple(up / np.linalg.norm(up)))
        self._place_view(up / np.linalg.norm(up))
        self._add_cameras()
        self._add_protocol_sector()
        self._build_gui(rounds)
        self.show_round(self.state.index)
        self.show_camera(key_of_view(run, self.state.picked[0]) if self.state.picked else
                         next(iter(self.frustums)))

    # -- scene --------------------------------------------------------------------------------
    def _camera_scale(self) -> float:
        centers = self.run.pool.cameras.centers.double()
        return 0.08 * float((centers - centers.mean(0)).norm(dim=1).mean())

    def _place_view(self, up: np.ndarray) -> None:
        """Start outside the ring of cameras, above it, looking at its centre."""
        centers = self.run.pool.cameras.centers.double().numpy()
        middle = centers.mean(0)
        radius = float(np.linalg.norm(centers - middle, axis=1).mean())
        first = centers[0] - middle
        side = first - (first @ up) * up
        side = side / max(np.linalg.norm(side), 1e-9)
        position, look_at = tuple(middle + 1.5 * radius * side + 0.9 * radius * up), tuple(middle)
        if self.client is not None:  # this tab's own camera
            cam = self.client.camera
            cam.position, cam.look_at, cam.up_direction = position, look_at, tuple(up)
        else:                        # where every new tab starts
            cam = self.server.initial_camera
            cam.position, cam.look_at, cam.up = position, look_at, tuple(up)

    def _add_cameras(self) -> None:
        scale = self._camera_scale()
        splits = [("pool", self.run.pool.cameras), ("test", self.run.test.cameras)]
        if self.run.captured is not None:
            splits.append(("captured", self.run.captured.cameras))
        for split, cams in splits:
            positions, wxyz = camera_poses(cams)
            ids = {"pool": pool_ids(self.run), "test": list(self.run.views.test_ids)}.get(split, list(range(len(cams))))
            for view in ids:
                key = CameraKey(split, view)
                handle = self.scene.add_camera_frustum(
                    f"/cameras/{split}/{view:04d}", fov=vertical_fov(cams), aspect=cams.width / cams.height,
                    scale=scale * (0.6 if split == "test" else 1.0), color=ROLE_COLOURS["test"],
                    wxyz=wxyz[view], position=positions[view])
                handle.on_click(lambda _event, key=key: self.show_camera(key))
                self.frustums[key] = handle

    def _add_protocol_sector(self) -> None:
        protocol = self.run.cfg.protocol
        if protocol.kind != "goal" or protocol.manifold.get("kind") != "sector":
            return
        manifold = resolved_manifold(protocol.manifold, self.run.scene,
                                     torch.tensor(self.run.views.up, dtype=torch.float64))
        self.scene.add_line_segments("/protocol_sector", sector_outline(manifold, self.run.pool.cameras),
                                            colors=ROLE_COLOURS["goal"], thickness=0.01 * self._camera_scale() * 12)

    def _show_model(self) -> None:
        arrays = splat_arrays(self.state.model)
        self.splat = self.scene.add_gaussian_splats("/splat", **arrays)

    # -- GUI ----------------------------------------------------------------------------------
    def _build_gui(self, rounds: int) -> None:
        gui, run = self.gui, self.run
        final = f"{run.final_psnr:.2f} dB" if run.final_psnr is not None else "running"
        gui.add_markdown(f"**{run.title}**  \nfinal PSNR {final} · {len(run.initial)} initial + "
                         f"{len(run.selected)} selected views · {len(run.views.test_ids)} test views")
        with gui.add_folder("Episode"):
            self.round_slider = gui.add_slider("Round", 0, max(rounds - 1, 1), 1, self.state.index,
                                               disabled=rounds == 1)
            self.round_text = gui.add_markdown("")
        self.round_slider.on_update(lambda _e: self.show_round(int(self.round_slider.value)))
        with gui.add_folder("Goal"):
            self.goal_kind = gui.add_dropdown("Goal", GOAL_KINDS, initial_value=GOAL_KINDS[0])
            sector = run.cfg.protocol.manifold if run.cfg.protocol.manifold.get("kind") == "sector" else {}
            self.goal_start = gui.add_number("Start angle (deg)", float(sector.get("start_deg", 0.0)),
                                             min=0.0, max=360.0, step=1.0)
            self.goal_width = gui.add_number("Width (deg)", float(sector.get("width_deg", 120.0)),
                                             min=1.0, max=360.0, step=1.0)
            self.goal_direction = gui.add_dropdown(
                "Direction", DIRECTIONS, initial_value=DIRECTIONS[0 if sector.get("clockwise", True) else 1])
            self.goal_views = gui.add_text("Picked views", "", hint="pool view ids, e.g. 3, 17, 40 "
                                           "(or show a camera and press 'Add the shown camera')")
            self.goal_probes = gui.add_number("Probes K", int(run.views.probes), min=1, step=1)
            self.add_view_button = gui.add_button("Add the shown camera to the picked views")
            self.score_button = gui.add_button("Score next view")
            self.goal_text = gui.add_markdown("Draw a goal and press *Score next view*.")
        self.score_button.on_click(lambda _e: self.score())
        self.add_view_button.on_click(lambda _e: self.add_shown_to_goal())
        with gui.add_folder("Camera"):
            names = [k.label for k in self.frustums]
            self.camera_choice = gui.add_dropdown("Camera view", names, initial_value=names[0])
            self.camera_text = gui.add_markdown("Click a camera, or choose one above.")
            blank = np.zeros((run.pool.cameras.height, run.pool.cameras.width, 3), np.uint8)
            self.image_truth = gui.add_image(blank, label="ground truth")
            self.image_render = gui.add_image(blank, label="render")
            self.image_variance = gui.add_image(blank, label="predictive variance")
        self.camera_choice.on_update(lambda _e: self._chosen(self.camera_choice.value))
        with gui.add_folder("Cameras"):
            self.camera_list = gui.add_markdown("")
            gui.add_markdown(LEGEND)

    def _key_of(self, label: str) -> CameraKey:
        split, view = label.split()
        return CameraKey(split, int(view))

    def _chosen(self, label: str) -> None:
        """The dropdown's choice (ignored when it only follows a camera shown otherwise)."""
        key = self._key_of(label)
        if key != self.shown:
            self.show_camera(key)

    # -- actions ------------------------------------------------------------------------------
    def show_round(self, index: int) -> None:
        """Show round ``index``: its model, its roles and colours, the shown camera re-rendered with
        it; a goal scored on another round's model is cleared (panel and scene agree)."""
        with self.lock:
            self.state = self.run.round_state(index)
            had_goal, self.goal = self.goal is not None, None
            if self.goal_sector is not None:
                self.goal_sector.remove()
                self.goal_sector = None
            if had_goal:
                self.goal_text.content = (f"Round changed to {index}: the goal's scores were for another "
                                          "round's model. Press *Score next view* to score it here.")
            self._show_model()
            self._show_landscape()
            self._colour()
            state = self.state
            model = "the final model (round models not kept: run with job.round_models=true)" \
                if state.model_is_final else "this round's model"
            self.round_text.content = (f"Round {index}: {len(state.taken)} views taken, PSNR "
                                       f"{state.psnr:.2f} dB, picked {', '.join(map(str, state.picked))}; "
                                       f"showing {model}")
            if self.shown is not None:  # the panel shows this round's model too
                self._show_camera(self.shown)

    def _show_landscape(self) -> None:
        """The score landscape the round's pose search saw: its evaluated poses as points at their
        camera centres, coloured by the score's standing (off-pool runs only)."""
        if self.landscape is not None:
            self.landscape.remove()
            self.landscape = None
        search = self.run.rounds[self.state.index].get("search") or {}
        if not search.get("evaluated"):
            return
        evaluated = torch.tensor(search["evaluated"], dtype=torch.float64)
        centres = self.run.pose_space.cameras(evaluated[:, :3]).centers.double().numpy()
        standing = score_ranks(dict(enumerate(evaluated[:, 3].tolist())), True)
        colours = np.array([standing_colour(standing[i]) for i in range(len(evaluated))], dtype=np.uint8)
        self.landscape = self.scene.add_point_cloud("/landscape", centres.astype(np.float32), colours,
                                                    point_size=0.25 * self._camera_scale())

    def _colour(self) -> None:
        state, goal = self.state, self.goal
        scores = goal.scores if goal is not None else state.scores
        low = True if goal is not None else lower_is_better(state.scores, state.picked)
        standing = score_ranks(scores, low)
        roles = camera_roles(self.run, state, goal)
        for view, (role, _caption) in roles.items():
            handle = self.frustums[key_of_view(self.run, view)]
            handle.visible = role != "later"  # a view captured in a later round is not there yet
            colour = standing_colour(standing[view]) if role == "candidate" and view in standing \
                else ROLE_COLOURS.get(role, (200, 200, 200))
            handle.color = colour
        self._label_picks(roles)
        self.camera_list.content = self._camera_listing(roles)

    def _label_picks(self, roles: dict[int, tuple[str, str]]) -> None:
        for handle in self.labels.values():
            handle.remove()
        self.labels = {}
        positions, _ = camera_poses(self.run.pool.cameras)
        captured, _ = camera_poses(self.run.captured.cameras) if self.run.captured is not None else (None, None)
        order = {view: k + 1 for k, view in enumerate(self.run.selected)}
        for view, (role, _caption) in roles.items():
            position = captured[view - self.run.first_captured] if self.run.is_captured(view) else positions[view]
            if role == "selected":
                text = f"#{order[view]}"
            elif role == "picked":
                text = "next best view" if self.goal is not None else f"next (#{order.get(view, '?')})"
            else:
                continue
            self.labels[view] = self.scene.add_label(f"/labels/{view:04d}", text, position=position)

    def _camera_listing(self, roles: dict[int, tuple[str, str]]) -> str:
        def ids(role):
            return ", ".join(str(v) for v, (r, _) in roles.items() if r == role) or "none"
        selected = sorted((v for v, (r, _) in roles.items() if r == "selected"),
                          key=self.run.selected.index)
        return "\n".join([
            f"- initial: {ids('initial')}",
            f"- selected (pick order): {', '.join(map(str, selected)) or 'none'}",
            f"- {'next best' if self.goal is not None else 'picked this round'}: {ids('picked')}",
            f"- probes: {ids('probe')}",
            f"- candidates: {sum(r == 'candidate' for r, _ in roles.values())} "
            f"(coloured by score: bright cyan = best, dark teal = worst)",
            f"- test views: {len(self.run.views.test_ids)}",
            *([f"- captured off the pool: {self._captured_list(roles) or 'none yet'}"]
              if self.run.captured is not None else []),
        ])

    def _captured_list(self, roles: dict[int, tuple[str, str]]) -> str:
        """The views captured off the pool so far (not the ones still to come)."""
        return ", ".join(str(v) for v, (r, _) in roles.items() if self.run.is_captured(v) and r != "later")

    def goal_manifold(self) -> dict:
        """The goal the GUI describes, in config form."""
        if self.goal_kind.value == "picked cameras":
            text = self.goal_views.value.replace(",", " ").split()
            try:
                views = [int(t) for t in text]
            except ValueError:
                raise ValueError(f"picked views must be integers, got {self.goal_views.value!r}") from None
            if not views:
                raise ValueError("pick at least one pool view for the goal")
            return {"kind": "poses", "view_ids": views}
        return {"kind": "sector", "start_deg": float(self.goal_start.value) % 360,
                "width_deg": float(self.goal_width.value),
                "clockwise": self.goal_direction.value == "clockwise"}

    def score(self) -> GoalScores | None:
        """Score the drawn goal on the shown round's model; the GUI shows the result or the error."""
        with self.lock:
            self.goal_text.content = "Scoring ..."
            try:
                manifold = self.goal_manifold()
                self.goal = score_goal(self.run, self.state, manifold, int(self.goal_probes.value))
            except ValueError as err:
                self.goal = None
                self.goal_text.content = f"**Cannot score:** {err}"
                return None
            self._draw_goal(manifold)
            self._colour()
            best = self.goal.best
            top = sorted(self.goal.scores.items(), key=lambda kv: kv[1])[:5]
            lines = [f"**Next best view: pool {best}** (GO-PRE score {self.goal.scores[best]:.6g}, "
                     f"{len(self.goal.probes)} probes, {len(self.goal.scores)} candidates, "
                     f"options {gopre_options(self.run) or 'defaults'})", "",
                     "| view | score |", "|---|---|"]
            lines += [f"| {view} | {value:.6g} |" for view, value in top]
            self.goal_text.content = "\n".join(lines)
            return self.goal

    def _draw_goal(self, manifold: dict) -> None:
        if self.goal_sector is not None:
            self.goal_sector.remove()
            self.goal_sector = None
        if manifold["kind"] != "sector":
            return
        resolved = resolved_manifold(manifold, self.run.scene, torch.tensor(self.run.views.up, dtype=torch.float64))
        assert isinstance(resolved, SectorManifold)
        self.goal_sector = self.scene.add_line_segments(
            "/goal_sector", sector_outline(resolved, self.run.pool.cameras), colors=ROLE_COLOURS["picked"],
            thickness=0.12 * self._camera_scale())

    def add_shown_to_goal(self) -> None:
        """Append the shown pool camera to the picked views of the goal (inspecting alone never
        edits the goal)."""
        key = self.shown
        if key is None or key.split != "pool":
            self.goal_text.content = "Show a pool camera first (test views cannot be part of a goal)."
            return
        views = self.goal_views.value.strip()
        if str(key.index) not in views.replace(",", " ").split():
            self.goal_views.value = f"{views}, {key.index}" if views else str(key.index)

    def variance(self) -> torch.Tensor:
        """S = 1 / (H_train + lambda) of the shown round's taken views, cached per round."""
        if self.state.index not in self.variances:
            g, run = self.state.model, self.run
            background = run.scene.background.to(g.means)
            lam = float(gopre_options(run).get("lam", POSTERIOR_LAMBDA))
            _, self.variances[self.state.index] = taken_views_posterior(
                g, run.cameras_of(self.state.taken), background, lam=lam)
        return self.variances[self.state.index]

    def show_camera(self, key: CameraKey) -> None:
        with self.lock:
            self._show_camera(key)

    def _show_camera(self, key: CameraKey) -> None:
        """The panel shows ``key`` with the shown round's model; the dropdown follows."""
        self.shown = key
        if self.camera_choice.value != key.label:
            self.camera_choice.value = key.label
        run, g = self.run, self.state.model
        split = {"pool": run.pool, "test": run.test, "captured": run.captured}[key.split]
        cams = split.cameras[[key.index]]
        background = run.scene.background.to(g.means)
        with torch.no_grad():
            image = render(g, cams, background).rgb[0]
        variance = predictive_variance_maps(g, cams, self.variance(), background)[0].sum(-1)
        self.image_truth.image = enlarged(to_uint8(split.images[key.index]))
        self.image_render.image = enlarged(to_uint8(image))
        self.image_variance.image = enlarged(to_uint8(colormap(variance)))
        role = ""
        if key.split in ("pool", "captured"):
            view = key.index + (run.first_captured if key.split == "captured" else 0)
            role = camera_roles(run, self.state, self.goal)[view][1]
            scores = self.goal.scores if self.goal is not None else self.state.scores
            if key.split == "pool" and key.index in scores:
                role += f", score {scores[key.index]:.6g}"
        self.camera_text.content = (f"**{key.label}** ({split.names[key.index]}) {role} · round "
                                    f"{self.state.index}'s model")


def per_client_viewers(run: EpisodeRun, server, start_round: int | None = None) -> dict[int, EpisodeViewer]:
    """One ``EpisodeViewer`` per connected browser tab, built when it connects and dropped when it
    leaves, so a second tab never starts with the first one's goal, round or camera."""
    viewers: dict[int, EpisodeViewer] = {}

    def connected(client) -> None:
        viewers[client.client_id] = EpisodeViewer(run, server, start_round, client)

    server.on_client_connect(connected)
    server.on_client_disconnect(lambda client: viewers.pop(client.client_id, None))
    return viewers

