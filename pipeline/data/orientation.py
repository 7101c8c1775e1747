"""Which way is up in a scene whose world frame is arbitrary (structure-from-motion): three estimates,
the choice, and a warning when they disagree.

- ``cameras``: the mean of the cameras' up directions (OpenCV: -y). Right when the photos were taken
  upright; 90 degrees off when the phone was held sideways and the images carry no orientation tag.
- ``plane``: the normal of the dominant plane of the points (RANSAC: the table, the floor), turned
  towards the cameras (they look down at it). Right when such a plane dominates the points.
- ``pca``: the smallest principal axis of the camera centres (nerfstudio's ``orientation_method
  pca``), turned towards the cameras' side of the points. Right for a walk around an object at about
  one height, whatever way the phone was held.
- an explicit vector ``[x, y, z]``.

``cameras`` stays the default (what every earlier result used); the reader's choice can be set by a
dataset entry (``up: plane`` or ``up: [0, 0, 1]``) or, for a capture, by ``gopre-data capture --up``
(kept in ``capture.json``). Whatever is chosen, the others are computed too; when the default axis
is more than ``DISAGREE_DEG`` from *every* other estimate, a warning says so. One estimate alone can
fail: on the alexander capture (a head in a gallery) the dominant plane of the points is a wall
(105 degrees from the cameras' axis, pca 21 degrees), so one disagreeing estimate is not enough.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor

from pipeline.cameras import Cameras

METHODS = ("cameras", "plane", "pca")
DISAGREE_DEG = 30.0
RANSAC_ITERATIONS = 400
RANSAC_INLIER_FRACTION = 0.01   # of the points' robust extent (the 5th-95th percentile box diagonal)
MAX_POINTS = 20_000             # points the plane is searched on (an evenly spaced subset beyond)


def camera_up(cameras: Cameras) -> Tensor:
    """[3] float64: the mean of the cameras' up directions (OpenCV y points down), normalised."""
    up = -cameras.viewmats[:, 1, :3].double().mean(0)
    if up.norm() < 1e-6:
        raise ValueError("cannot estimate the up axis: camera up vectors cancel out")
    return up / up.norm()


def _towards_cameras(normal: Tensor, cameras: Cameras, points: Tensor | None) -> Tensor:
    """``normal`` signed so that the cameras lie on its positive side of the points (or, without
    points, so that it agrees with the cameras' own up)."""
    centres = cameras.centers.double()
    if points is not None and len(points):
        side = float((centres.mean(0) - points.double().median(0).values) @ normal)
    else:
        side = float(camera_up(cameras) @ normal)
    return normal if side >= 0 else -normal


def plane_up(points: Tensor, cameras: Cameras, seed: int = 0) -> tuple[Tensor, float]:
    """The dominant plane's unit normal [3] (float64, towards the cameras) and its inlier fraction,
    by RANSAC on ``points`` [P, 3] with a least-squares refit on the inliers."""
    pts = points.double()
    if len(pts) < 3:
        raise ValueError(f"plane: {len(pts)} points; at least 3 are needed")
    if len(pts) > MAX_POINTS:
        pts = pts[torch.linspace(0, len(pts) - 1, MAX_POINTS).long()]
    lo, hi = torch.quantile(pts, 0.05, dim=0), torch.quantile(pts, 0.95, dim=0)
    threshold = RANSAC_INLIER_FRACTION * float((hi - lo).norm())
    gen = torch.Generator().manual_seed(seed)
    best, best_count = None, -1
    for _ in range(RANSAC_ITERATIONS):
        a, b, c = pts[torch.randperm(len(pts), generator=gen)[:3]]
        normal = torch.linalg.cross(b - a, c - a)
        if normal.norm() < 1e-12:
            continue
        normal = normal / normal.norm()
        count = int((((pts - a) @ normal).abs() < threshold).sum())
        if count > best_count:
            best, best_count = (a, normal), count
    if best is None:
        raise ValueError("plane: the points are collinear")
    a, normal = best
    inliers = pts[((pts - a) @ normal).abs() < threshold]
    _, _, vt = torch.linalg.svd(inliers - inliers.mean(0), full_matrices=False)
    return _towards_cameras(vt[-1] / vt[-1].norm(), cameras, points), best_count / len(pts)


def pca_up(cameras: Cameras, points: Tensor | None = None) -> Tensor:
    """The smallest principal axis [3] of the camera centres, towards the cameras' side of the points."""
    centres = cameras.centers.double()
    if len(centres) < 3:
        raise ValueError(f"pca: {len(centres)} cameras; at least 3 are needed")
    _, _, vt = torch.linalg.svd(centres - centres.mean(0), full_matrices=False)
    return _towards_cameras(vt[-1] / vt[-1].norm(), cameras, points)


def angle_deg(a: Tensor, b: Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a.double() @ b.double())))))


@dataclass
class Orientation:
    """The up axis a scene uses, how it was chosen, and the other estimates beside it."""

    up: list[float]
    method: str                                   # cameras | plane | pca | given
    estimates: dict = field(default_factory=dict)  # method -> [3] (those that could be computed)
    angles_deg: dict = field(default_factory=dict)  # method -> angle to the chosen up
    plane_inliers: float | None = None

    explicit: bool = False                        # chosen by a dataset entry or --up (no warning then)

    @property
    def disagreements(self) -> dict[str, float]:
        """The other estimates, when the axis in use is more than ``DISAGREE_DEG`` from every one of
        them (one estimate can fail alone: a gallery's wall outweighs its floor in the points)."""
        others = {m: a for m, a in self.angles_deg.items() if m != self.method}
        return others if others and all(a > DISAGREE_DEG for a in others.values()) else {}

    def warning(self) -> str | None:
        """One line when the default axis is more than ``DISAGREE_DEG`` from every other estimate."""
        if self.explicit or not self.disagreements:
            return None
        others = ", ".join(f"{m} {a:.0f} deg away" for m, a in self.disagreements.items())
        return (f"the up axis ({self.method}) disagrees with the other estimates ({others}; more than "
                f"{DISAGREE_DEG:.0f} deg): a phone held sideways without an orientation tag gives a camera up axis "
                "90 deg off; set it with the dataset entry's up: plane | pca | [x, y, z] (or gopre-data capture --up)")

    def to_dict(self) -> dict:
        return {**asdict(self), "warning": self.warning()}


def parse_up(value) -> str | list[float] | None:
    """A dataset entry's or a flag's ``up``: None, a method name, or a non-zero vector [x, y, z]."""
    if value is None or value == "":
        return None
    if isinstance(value, str):
        text = value.strip()
        if text in METHODS:
            return text
        try:
            value = [float(x) for x in text.strip("[]").split(",")]
        except ValueError:
            raise ValueError(f"up: expected one of {list(METHODS)} or a vector x,y,z, got {value!r}") from None
    if isinstance(value, (list, tuple)):
        vector = [float(x) for x in value]
        if len(vector) != 3 or not all(math.isfinite(x) for x in vector) or math.hypot(*vector) < 1e-9:
            raise ValueError(f"up: a vector must be three finite numbers, not all zero, got {list(value)}")
        norm = math.hypot(*vector)
        return [x / norm for x in vector]
    raise ValueError(f"up: expected one of {list(METHODS)} or a vector [x, y, z], got {value!r}")


def orientation(cameras: Cameras, points: Tensor | None, choice: str | list[float] | None = None) -> Orientation:
    """Every estimate the scene allows, and the chosen one (``choice``: a method, a vector, or None
    for ``cameras``)."""
    estimates: dict[str, Tensor] = {"cameras": camera_up(cameras)}
    inliers = None
    if points is not None and len(points) >= 3:
        estimates["plane"], inliers = plane_up(points, cameras)
    if len(cameras) >= 3:
        estimates["pca"] = pca_up(cameras, points)
    choice = parse_up(choice)
    explicit, choice = choice is not None, choice or "cameras"
    if isinstance(choice, list):
        up, method = torch.tensor(choice, dtype=torch.float64), "given"
    else:
        if choice not in estimates:
            raise ValueError(f"up: {choice!r} cannot be estimated here ({'no points' if choice == 'plane' else 'too few cameras'})")
        up, method = estimates[choice], choice
    return Orientation([float(x) for x in up], method, {m: [round(float(x), 6) for x in v] for m, v in estimates.items()},
                       {m: round(angle_deg(up, v), 2) for m, v in estimates.items()},
                       None if inliers is None else round(inliers, 4), explicit)
