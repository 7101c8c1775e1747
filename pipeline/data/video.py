"""Frames of a video for structure-from-motion: decoded with PyAV (``av``, a wheel that ships its
own FFmpeg libraries), the sharpest frame of each of ``count`` equal stretches kept.

Sharpness is the variance of a 4-neighbour Laplacian of the frame's luminance at <= 320 px (a
blurred frame, from motion or focus, has little high-frequency energy); choosing one frame per
stretch keeps them spread evenly over the walk around the object, as ``ns-process-data`` spreads
its frames, while skipping the blurred ones it would take.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.data.images import DataError


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the luminance of an [H, W, 3] uint8 frame."""
    grey = rgb[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    step = max(1, max(grey.shape) // 320)
    grey = grey[::step, ::step]
    lap = (grey[1:-1, :-2] + grey[1:-1, 2:] + grey[:-2, 1:-1] + grey[2:, 1:-1] - 4 * grey[1:-1, 1:-1])
    return float(lap.var())


def choose_sharp(scores: list[float], count: int) -> list[int]:
    """Indices of the sharpest frame in each of ``count`` equal stretches of the frames (all of them
    when there are no more than ``count``), in order."""
    n = len(scores)
    if n <= count:
        return list(range(n))
    edges = np.linspace(0, n, count + 1).round().astype(int)
    return [int(lo + np.argmax(scores[lo:hi])) for lo, hi in zip(edges[:-1], edges[1:]) if hi > lo]


def sharp_frames(path: Path, count: int, say: Callable[[str], None] = lambda line: None) -> list[np.ndarray]:
    """The chosen frames of the video at ``path`` as [H, W, 3] uint8 arrays."""
    import av
    if count < 3:
        raise DataError(f"--frames must be at least 3, got {count}")
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as err:
        raise DataError(f"{path}: cannot open the video ({err})") from None
    with container:
        if not container.streams.video:
            raise DataError(f"{path}: has no video stream")
        stream = container.streams.video[0]
        total = stream.frames or 0
        scores: list[float] = []
        for k, frame in enumerate(container.decode(stream)):  # first pass: sharpness only
            scores.append(sharpness(frame.to_ndarray(format="rgb24")))
            if total and (k + 1) % max(1, total // 4) == 0:
                say(f"video: {k + 1}/{total} frames scored for sharpness")
    keep = set(choose_sharp(scores, count))
    if not keep:
        raise DataError(f"{path}: no frame could be decoded")
    frames = []
    with av.open(str(path)) as container:  # second pass: keep the chosen frames
        for k, frame in enumerate(container.decode(container.streams.video[0])):
            if k in keep:
                frames.append(frame.to_ndarray(format="rgb24"))
    say(f"video: kept {len(frames)} of {len(scores)} frames (the sharpest of each of {count} stretches)")
    return frames
