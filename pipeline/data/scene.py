"""A posed image collection as every reader returns it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.data.images import ImageStore


@dataclass
class Split:
    """One split: cameras [C] at the working resolution and their lazily loaded images."""

    cameras: Cameras
    images: ImageStore
    names: list[str]

    def __len__(self) -> int:
        return len(self.names)


@dataclass(frozen=True)
class SceneTraits:
    """What the protocols and the pose space need to know of a scene, set by its reader
    (``pipeline.data.readers``) instead of asked of its format.

    kind: ``object`` (photographed all around it: the pose space is the whole shell, the scene's
    radius bounds it) | ``unbounded`` (cameras inside the scene). up: ``z`` (+z is up) |
    ``estimated`` (from the cameras, ``manifolds.estimate_up``). split: ``given`` (the files' train
    and test splits) | ``llff`` (every 8th image in name order held out)."""

    kind: str = "unbounded"
    up: str = "estimated"
    split: str = "llff"


OBJECT = SceneTraits(kind="object", up="z", split="given")   # a Blender object scene
REAL = SceneTraits(kind="unbounded", up="estimated", split="llff")  # a capture (COLMAP, nerfstudio)
FORMAT_TRAITS = {"blender": OBJECT, "nerfstudio": REAL, "colmap": REAL}  # each reader's (``readers.READERS``)


def traits_of(format: str) -> SceneTraits:
    """A format's traits (an unknown format: a real scene's)."""
    return FORMAT_TRAITS.get(format, REAL)


@dataclass
class Scene:
    """A scene: named splits, a background colour [3], and optional points [P, 3] with colours."""

    name: str
    format: str
    root: Path
    splits: dict[str, Split]
    background: Tensor
    points: Tensor | None = None
    point_colors: Tensor | None = None
    box: tuple[Tensor, Tensor] | None = None  # initialisation box when there are no points
    info: dict = field(default_factory=dict)
    traits: SceneTraits | None = None        # None: its format's (``FORMAT_TRAITS``)
    # per split, [C] mask files (white = the object, kept; black = ignored) when the capture has them
    masks: dict[str, list[Path]] | None = None

    def __post_init__(self) -> None:
        if self.traits is None:
            self.traits = traits_of(self.format)

    def split(self, name: str) -> Split:
        if name not in self.splits:
            raise KeyError(f"{self.root}: no split {name!r}; available: {sorted(self.splits)}")
        return self.splits[name]

    def all_cameras(self) -> Cameras:
        return Cameras.cat([s.cameras for s in self.splits.values()])

    def bounds(self) -> tuple[Tensor, Tensor]:
        """The initialisation box: explicit, else around the points, else the cameras' centre."""
        if self.box is not None:
            return self.box
        if self.points is not None and len(self.points):
            lo, hi = torch.quantile(self.points, 0.01, dim=0), torch.quantile(self.points, 0.99, dim=0)
            return lo, hi
        centers = self.all_cameras().centers
        mid = centers.mean(0)
        radius = (centers - mid).norm(dim=1).mean()
        return mid - 0.5 * radius, mid + 0.5 * radius
