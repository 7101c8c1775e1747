"""What the viewer draws, as plain arrays: camera poses, the splat, the target sector, colours.

Viser's camera frustums use the OpenCV camera frame (x right, y down, z forward), as our cameras
do, so a frustum's pose is the camera-to-world transform: position = camera centre,
rotation = R^T of the world-to-camera ``viewmat``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.cameras import Cameras
from pipeline.data.manifolds import SectorManifold, plane_basis
from pipeline.splat import Gaussians
from pipeline.splat.gaussians import SH_C0, scaled_rotations

ROLE_COLOURS = {                       # RGB 0-255
    "initial": (40, 90, 230),
    "selected": (20, 160, 60),
    "picked": (235, 50, 30),           # this round's pick (or the next best view of a drawn goal)
    "probe": (170, 60, 210),
    "test": (150, 150, 150),
    "goal": (255, 150, 0),             # the drawn target sector
}


def rotmat_to_wxyz(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) [C, 4] of rotation matrices [C, 3, 3] (Shepperd's method:
    the largest of the four diagonal combinations is the pivot, so no division is ill-conditioned)."""
    rot = np.asarray(rot, dtype=np.float64)
    out = np.empty((rot.shape[0], 4))
    for i, m in enumerate(rot):
        trace = m[0, 0] + m[1, 1] + m[2, 2]
        pivot = int(np.argmax([trace, m[0, 0], m[1, 1], m[2, 2]]))
        if pivot == 0:
            s = 2 * math.sqrt(1 + trace)
            q = (s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
        elif pivot == 1:
            s = 2 * math.sqrt(1 + m[0, 0] - m[1, 1] - m[2, 2])
            q = ((m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
        elif pivot == 2:
            s = 2 * math.sqrt(1 + m[1, 1] - m[0, 0] - m[2, 2])
            q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s)
        else:
            s = 2 * math.sqrt(1 + m[2, 2] - m[0, 0] - m[1, 1])
            q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4)
        q = np.array(q)
        out[i] = q if q[0] >= 0 else -q
    return out


def camera_poses(cameras: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """Frustum poses: positions [C, 3] (camera centres) and orientations wxyz [C, 4] (camera to
    world, OpenCV frame)."""
    vm = cameras.viewmats.detach().double().cpu().numpy()
    return cameras.centers.detach().double().cpu().numpy(), rotmat_to_wxyz(vm[:, :3, :3].transpose(0, 2, 1))


def vertical_fov(cameras: Cameras) -> float:
    """Vertical field of view in radians of the first camera (the batch shares its image size)."""
    return float(2 * math.atan(cameras.height / (2 * float(cameras.Ks[0, 1, 1]))))


def splat_arrays(g: Gaussians) -> dict[str, np.ndarray]:
    """The splat as viser draws it: centres [N, 3], world covariances (R S)(R S)^T [N, 3, 3],
    colours [N, 3] from the DC term only (a view-independent colour), opacities [N, 1]."""
    with torch.no_grad():
        m = scaled_rotations(g.log_scales.double(), g.quats.double())
        cov = m @ m.transpose(1, 2)
        rgb = (g.sh0[:, 0].double() * SH_C0 + 0.5).clamp(0, 1)
        return {"centers": g.means.double().numpy().astype(np.float32),
                "covariances": cov.numpy().astype(np.float32),
                "rgbs": rgb.numpy().astype(np.float32),
                "opacities": g.opacities.double()[:, None].numpy().astype(np.float32)}


def sector_outline(manifold: SectorManifold, cameras: Cameras, points: int = 48) -> np.ndarray:
    """Line segments [S, 2, 3] drawing a resolved sector at the cameras' mean in-plane radius and
    mean height: the arc from its start to its end azimuth and the two spokes from the centre."""
    if manifold.up is None or manifold.center is None:
        raise ValueError("sector_outline: resolve the manifold on the scene's cameras first")
    up = torch.tensor(manifold.up, dtype=torch.float64)
    up = up / up.norm()
    center = torch.tensor(manifold.center, dtype=torch.float64)
    e1, e2 = plane_basis(up, manifold.reference)
    offsets = cameras.centers.double() - center
    height = float((offsets @ up).mean())
    radius = float((offsets - (offsets @ up)[:, None] * up).norm(dim=1).mean())
    first = manifold.start_deg - manifold.width_deg if manifold.clockwise else manifold.start_deg
    angles = torch.deg2rad(torch.linspace(first, first + manifold.width_deg, points, dtype=torch.float64))
    base = center + height * up
    arc = base + radius * (torch.cos(angles)[:, None] * e1 + torch.sin(angles)[:, None] * e2)
    segments = [torch.stack([arc[i], arc[i + 1]]) for i in range(points - 1)]
    segments += [torch.stack([base, arc[0]]), torch.stack([base, arc[-1]])]
    return torch.stack(segments).numpy()


def score_ranks(scores: dict[int, float], lower_is_better: bool) -> dict[int, float]:
    """Each candidate's standing in [0, 1]: 1 = the best score, 0 = the worst (by rank, so one
    extreme score does not wash out the rest); ties share a standing."""
    if not scores:
        return {}
    values = sorted(set(scores.values()), reverse=lower_is_better)  # worst first
    if len(values) == 1:
        return {i: 1.0 for i in scores}
    place = {v: k / (len(values) - 1) for k, v in enumerate(values)}
    return {i: place[v] for i, v in scores.items()}


def lower_is_better(scores: dict[int, float], picked: list[int]) -> bool:
    """Which way a strategy ranks, read off its own pick: the picked candidate holds the minimum
    (GO-PRE's argmin) or the maximum (information gain) of the scores."""
    if not picked or picked[0] not in scores:
        return True
    return scores[picked[0]] <= min(scores.values())


CANDIDATE_RAMP = ((0, 70, 80), (130, 255, 255))  # dark teal (worst) -> bright cyan (best)


def standing_colour(standing: float) -> tuple[int, int, int]:
    """A remaining candidate's colour by its score's standing in [0, 1]: dark teal (worst) to
    bright cyan (best), a ramp no role colour lies near (initial, selected, picked, probe, test)."""
    lo, hi = (np.array(c, dtype=np.float64) for c in CANDIDATE_RAMP)
    rgb = lo + min(max(standing, 0.0), 1.0) * (hi - lo)
    return tuple(int(round(c)) for c in rgb)
