"""``gopre-data cameras SCENE --out FIG.png``: a scene's cameras as a figure, in the frame of its up
axis: from above (azimuth about the up axis) and from the side, every camera's centre and viewing
direction, the goal-oriented protocol's 120-degree sector and its views highlighted, the test
views marked, a subsample of the model's points in grey. Shows a capture's recovered poses
without any of its images."""

from __future__ import annotations

from pathlib import Path

import torch

from pipeline.data.load import load_scene
from pipeline.data.manifolds import plane_basis
from pipeline.data.protocols import ProtocolConfig, build_protocol, resolved_manifold, scene_up


def camera_figure(scene_path: Path, out: Path, max_points: int = 4000, up_choice: str | None = None) -> dict:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    scene = load_scene(scene_path, width=64)
    goal = build_protocol(scene, ProtocolConfig(kind="goal", up=up_choice))
    pool = scene.split(goal.pool_split).cameras
    up = scene_up(scene, scene.all_cameras(), goal_up := ProtocolConfig(up=up_choice).up)
    e1, e2 = plane_basis(up, 0)
    centre = pool.centers.double().mean(0)
    inside = set(goal.probe_ids) | set(goal.test_ids)
    manifold = resolved_manifold(ProtocolConfig().manifold, scene, up)
    in_sector = manifold.contains(pool).tolist()
    frame = torch.stack([e1, e2, up])                      # world -> (x, y, up)
    c = (pool.centers.double() - centre) @ frame.T          # [C, 3]
    d = pool.viewmats[:, 2, :3].double() @ frame.T          # optical axes
    radius = float(c[:, :2].norm(dim=1).max())
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    if scene.points is not None and len(scene.points):
        pts = (scene.points.double() - centre) @ frame.T
        keep = torch.randperm(len(pts), generator=torch.Generator().manual_seed(0))[:max_points]
        pts = pts[keep]
        near = pts[:, :2].norm(dim=1) < 1.5 * radius
        axes[0].scatter(pts[near, 0], pts[near, 1], s=0.5, c="0.75", zorder=0)
        axes[1].scatter(pts[near, 0], pts[near, 2], s=0.5, c="0.75", zorder=0)
    colours = ["tab:orange" if s else "tab:blue" for s in in_sector]
    test = set(goal.test_ids)
    for ax, (i, j), title in ((axes[0], (0, 1), "from above (up axis out of the page)"),
                              (axes[1], (0, 2), "from the side (up axis vertical)")):
        ax.quiver(c[:, i], c[:, j], d[:, i], d[:, j], color=colours, angles="xy", scale_units="xy",
                  scale=4 / radius, width=0.004)
        ax.scatter(c[:, i], c[:, j], c=colours, s=12)
        marked = [k for k in range(len(c)) if k in test]
        ax.scatter(c[marked, i], c[marked, j], facecolors="none", edgecolors="k", s=60, label="goal test views")
        ax.set_aspect("equal")
        ax.set_title(title)
        ax.set_xlabel("x (world x projected on the ground plane)")
        ax.set_ylabel("y" if j == 1 else "up")
    axes[0].plot([], [], "o", color="tab:orange", label="inside the 120-degree goal sector")
    axes[0].plot([], [], "o", color="tab:blue", label="outside")
    axes[0].legend(loc="lower left", fontsize=8)
    how = (f"up axis: {goal_up if isinstance(goal_up, str) else 'given'}" if goal_up is not None
           else f"up axis: {scene.info['up']} (capture.json)" if scene.info.get("up") is not None
           else "up axis estimated from the cameras" if scene.traits is not None and scene.traits.up == "estimated"
           else "up axis +z")
    fig.suptitle(f"{scene.name}: {len(pool)} cameras ({scene.format}), {how}")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return {"written": str(out), "cameras": len(pool), "in_sector": int(sum(in_sector)),
            "goal_test_views": len(goal.test_ids), "goal_probe_pool": len(goal.probe_ids), "up": up.tolist(),
            "inside_ids": len(inside)}
