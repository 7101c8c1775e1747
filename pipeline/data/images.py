"""Lazy image loading with a memory budget: a scene's images are read on demand, resized to the
working resolution, composited on the background, and kept in an LRU cache of bounded size."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor


class DataError(ValueError):
    """Bad input data; the message names the file or setting and what is wrong."""


def read_image(path: Path, size: tuple[int, int] | None, background: Tensor) -> Tensor:
    """Read ``path`` as [H, W, 3] float32 in [0, 1]; RGBA is composited over ``background`` [3].

    size: (width, height) to resize to (Lanczos; alpha is premultiplied by Pillow), or None.
    """
    try:
        with Image.open(path) as im:
            im.load()
            img = im.convert("RGBA") if im.mode in ("RGBA", "LA", "P") else im.convert("RGB")
    except FileNotFoundError:
        raise DataError(f"{path}: image file not found") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read image ({err})") from None
    return image_tensor(img, size, background)


def image_tensor(img: Image.Image, size: tuple[int, int] | None, background: Tensor) -> Tensor:
    """A decoded RGB or RGBA image as the readers return it: resized to ``size`` (width, height;
    Lanczos, alpha premultiplied by Pillow) and composited over ``background`` [3]: [H, W, 3]
    float32 in [0, 1]. The capture simulators (``pipeline.world``) process their renders by it."""
    if size is not None and img.size != tuple(size):
        img = img.resize(tuple(size), Image.Resampling.LANCZOS)
    arr = torch.from_numpy(np.asarray(img, dtype=np.float32) / 255.0)
    if arr.shape[-1] == 4:
        rgb, alpha = arr[..., :3], arr[..., 3:]
        return rgb * alpha + background.to(arr.dtype) * (1 - alpha)
    return arr


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file without decoding it."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DataError(f"{path}: image file not found") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read image ({err})") from None


class ImageStore:
    """Images of one split, loaded on demand at ``size`` and cached up to ``budget_mb``."""

    def __init__(self, paths: list[Path], size: tuple[int, int], background: Tensor,
                 budget_mb: float = 1024.0, source_size: tuple[int, int] | None = None):
        self.paths, self.size, self.background = list(paths), size, background
        self.source_size = source_size  # every file must have this size (None: not checked)
        if source_size is not None and size[0] > source_size[0]:
            raise DataError(f"{Path(self.paths[0]).parent}: training width {size[0]} px is wider than the "
                            f"images ({source_size[0]} px): it would only upsample them (set splat.image_width "
                            f"<= {source_size[0]}, or null for the images' own width)")
        self.budget_bytes = budget_mb * 2 ** 20
        self._cache: OrderedDict[int, Tensor] = OrderedDict()
        self._bytes = 0

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> Tensor:
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        if self.source_size is not None and image_size(self.paths[index]) != tuple(self.source_size):
            got = image_size(self.paths[index])
            raise DataError(f"{self.paths[index]}: image is {got[0]}x{got[1]}, the scene's images are "
                            f"{self.source_size[0]}x{self.source_size[1]} (inconsistent sizes)")
        img = read_image(self.paths[index], self.size, self.background)
        expected = (self.size[1], self.size[0])
        if tuple(img.shape[:2]) != expected:
            raise DataError(f"{self.paths[index]}: image is {img.shape[1]}x{img.shape[0]}, "
                            f"expected {self.size[0]}x{self.size[1]}")
        self._cache[index] = img
        self._bytes += img.numel() * img.element_size()
        while self._bytes > self.budget_bytes and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._bytes -= old.numel() * old.element_size()
        return img

    def check_decodable(self, indices: list[int]) -> list[str]:
        """Decode the images at ``indices`` (without caching them): one error message per file
        that cannot be read at the store's size (zero-byte, truncated, wrong size ...)."""
        errors = []
        for i in indices:
            try:
                if self.source_size is not None and image_size(self.paths[i]) != tuple(self.source_size):
                    got = image_size(self.paths[i])
                    raise DataError(f"{self.paths[i]}: image is {got[0]}x{got[1]}, the scene's images "
                                    f"are {self.source_size[0]}x{self.source_size[1]}")
                read_image(self.paths[i], self.size, self.background)
            except DataError as err:
                errors.append(str(err))
        return errors

    def subset(self, indices: list[int]) -> "ImageStore":
        """A store over some of these images (its own cache, the same budget)."""
        return ImageStore([self.paths[i] for i in indices], self.size, self.background,
                          self.budget_bytes / 2 ** 20, self.source_size)

    def stack(self, indices: list[int] | None = None) -> Tensor:
        """[C, H, W, 3] for ``indices`` (all by default)."""
        indices = range(len(self)) if indices is None else indices
        return torch.stack([self[i] for i in indices])


def read_mask(path: Path, size: tuple[int, int]) -> Tensor:
    """A mask file as [H, W] float32 in {0, 1} at ``size`` (W, H): white (>= 128) = kept, resized
    by the nearest pixel so it stays binary; an unreadable file is an error naming it."""
    try:
        with Image.open(path) as im:
            im = im.convert("L")
            if im.size != tuple(size):
                im = im.resize(tuple(size), Image.NEAREST)
            values = np.asarray(im)
    except FileNotFoundError:
        raise DataError(f"{path}: mask file not found") from None
    except (OSError, UnidentifiedImageError) as err:
        raise DataError(f"{path}: cannot read mask ({err})") from None
    return torch.from_numpy((values >= 128).astype(np.float32))
