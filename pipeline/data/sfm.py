"""Structure-from-motion with pycolmap on the CPU, from prepared images to the largest model:
SIFT features (one shared SIMPLE_RADIAL camera), matching (exhaustive, along a walk with a loop
skeleton: ``loop_pairs``, or sequential) and incremental mapping, with progress lines read from
COLMAP's own log (``LogProgress``). ``capture`` makes scenes with it; ``geometry_check`` runs it on a
subset to check a model."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Callable

from pipeline.data.images import DataError

NEIGHBOURS = 10              # each photo with its next 10 in name order (the bonsai re-staging's)
SKELETON_EVERY = 5           # every pair among every 5th photo (292 photos: 4,461 pairs, not 42,486)
PROGRESS_SECONDS = 20.0      # a progress line during features and matching at most this often

Progress = Callable[[str], None]


class CaptureError(DataError):
    """A capture that cannot become a scene; the message names the files."""


def loop_pairs(names: list[str], neighbours: int = NEIGHBOURS, skeleton_every: int = SKELETON_EVERY
               ) -> list[tuple[str, str]]:
    """The pairs the loop matcher matches: each image with its ``neighbours`` next in name order,
    plus every pair among every ``skeleton_every``-th image; each pair once, in a fixed order."""
    ordered = sorted(names)
    pairs = {(i, j) for i in range(len(ordered)) for j in range(i + 1, min(i + 1 + neighbours, len(ordered)))}
    skeleton = range(0, len(ordered), skeleton_every)
    pairs |= {(i, j) for i in skeleton for j in skeleton if i < j}
    return [(ordered[i], ordered[j]) for i, j in sorted(pairs)]


class LogProgress:
    """A line every ``PROGRESS_SECONDS`` while COLMAP extracts or matches: how far its own log says it
    is (``Processed file [k/n]``, ``Processing block [...]``), read from its log files in a background
    thread. Never the database: a second SQLite library in the same process breaks SQLite's locking
    (each copy's POSIX locks release the other's) and crashed pycolmap with SIGBUS while matching."""

    PATTERNS = {"features": re.compile(r"Processed file \[(\d+/\d+)\]"),
                "matching": re.compile(r"Processing block \[([\d/, ]+)\]")}

    def __init__(self, log_dir: Path, stage: str, say: Progress, total: str):
        import threading
        self.log_dir, self.stage, self.say, self.total = log_dir, stage, say, total
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def last(self) -> str | None:
        """The stage's last progress mark in the newest log file (None before the first)."""
        logs = sorted(self.log_dir.glob("*INFO*"), key=lambda p: p.stat().st_mtime) if self.log_dir.is_dir() else []
        if not logs:
            return None
        try:
            text = logs[-1].read_text(errors="replace")[-200_000:]
        except OSError:
            return None
        found = self.PATTERNS[self.stage].findall(text)
        return found[-1] if found else None

    def run(self) -> None:
        start = time.perf_counter()
        while not self.stop.wait(PROGRESS_SECONDS):
            mark = self.last()
            if mark is not None:
                what = "images" if self.stage == "features" else "block"
                self.say(f"{self.stage}: {what} {mark} ({self.total}, {time.perf_counter() - start:.0f} s)")

    def __enter__(self) -> "LogProgress":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join()


def quiet_colmap(log_dir: Path) -> None:
    """COLMAP's own log (a line per image and pair) goes to files in ``log_dir``, not the console:
    the console gets this module's stage lines."""
    import pycolmap
    log_dir.mkdir(parents=True, exist_ok=True)
    pycolmap.logging.logtostderr = False
    pycolmap.logging.alsologtostderr = False
    pycolmap.logging.stderrthreshold = pycolmap.logging.ERROR  # type: ignore[assignment]  # a Level, stubbed as int
    pycolmap.logging.log_dir = str(log_dir)


def reconstruct(work: Path, names: list[str], matcher: str, say: Progress, seconds: dict,
                min_num_matches: int | None = None, seed: int | None = None) -> tuple:
    """SIFT, matching and incremental mapping; returns (largest model, the others' sizes).
    ``min_num_matches``: the fewest verified matches that link two images in the mapping (COLMAP's
    default 15 when None); ``seed``: COLMAP's random seed (its RANSAC; the result still varies with
    thread timing)."""
    import pycolmap
    options = pycolmap.IncrementalPipelineOptions()
    if min_num_matches is not None:
        options.min_num_matches = min_num_matches
    if seed is not None:
        pycolmap.set_random_seed(seed)
        options.random_seed = seed
    quiet_colmap(work / "colmap_logs")
    db, images_dir = work / "database.db", work / "images"
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    say(f"features: SIFT on {len(names)} images ...")
    logs = work / "colmap_logs"
    with LogProgress(logs, "features", say, f"{len(names)} images"):
        pycolmap.extract_features(db, images_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, device=pycolmap.Device.cpu)
    seconds["features"] = round(time.perf_counter() - start, 1)
    start = time.perf_counter()
    pairs = pair_count(names, matcher)
    say(f"matching: {matcher} ({pairs if pairs is not None else 'neighbouring'} pairs) ...")
    with LogProgress(logs, "matching", say, f"{pairs} pairs" if pairs else "neighbouring pairs"):
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        elif matcher == "loop":
            pairs_file = work / "pairs.txt"
            pairs_file.write_text("".join(f"{a} {b}\n" for a, b in loop_pairs(names)))
            pycolmap.match_image_pairs(db, pairing_options=pycolmap.ImportedPairingOptions(
                match_list_path=str(pairs_file)), device=pycolmap.Device.cpu)
        else:
            pycolmap.match_sequential(db, device=pycolmap.Device.cpu)
    seconds["matching"] = round(time.perf_counter() - start, 1)
    start = time.perf_counter()
    registered = [0]

    def next_image():
        registered[0] += 1
        if registered[0] % max(1, len(names) // 10) == 0:
            say(f"mapping: {min(registered[0], len(names))}/{len(names)} images tried (a retried image counts again)")
    models = pycolmap.incremental_mapping(db, images_dir, work / "sparse", options=options,
                                          next_image_callback=next_image)
    seconds["mapping"] = round(time.perf_counter() - start, 1)
    if not models:
        raise CaptureError(f"{work / 'images'}: structure-from-motion registered no model (too few matches: "
                           "more overlap between photos, more texture, or a sharper capture)")
    ranked = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    others = [r.num_reg_images() for r in ranked[1:]]
    if others:
        say(f"mapping: {len(ranked)} disconnected models; kept the largest ({ranked[0].num_reg_images()} images), "
            f"left out models of {others} images (capture.json lists them)")
    return ranked[0], others


def pair_count(names: list[str], matcher: str) -> int | None:
    """How many pairs the matcher matches (None: sequential, which COLMAP decides)."""
    if matcher == "exhaustive":
        return len(names) * (len(names) - 1) // 2
    return len(loop_pairs(names)) if matcher == "loop" else None
