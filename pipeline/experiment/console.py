"""The sweep's console: every progress line, note and warning of the driver goes through
``logging`` (logger ``pipeline.sweep``), printed to stdout as plain lines and, while a sweep runs,
written with a timestamp into ``<output_dir>/sweep.log`` (what a detached run left behind)."""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from pathlib import Path

LOG = logging.getLogger("pipeline.sweep")
LOG_FILE = "sweep.log"


class _CurrentStdout(logging.StreamHandler):
    """A handler on whatever ``sys.stdout`` is at the time of each line (so a redirected or
    captured stdout sees the lines too)."""

    def __init__(self) -> None:
        super().__init__(sys.stdout)

    @property
    def stream(self):
        return sys.stdout

    @stream.setter
    def stream(self, value) -> None:  # logging sets it once at construction; stdout is read live
        pass


def console() -> logging.Logger:
    """The driver's logger, with its stdout handler attached (once)."""
    if not any(isinstance(h, _CurrentStdout) for h in LOG.handlers):
        handler = _CurrentStdout()
        handler.setFormatter(logging.Formatter("%(message)s"))
        LOG.addHandler(handler)
        LOG.setLevel(logging.INFO)
        LOG.propagate = False
    return LOG


@contextmanager
def sweep_log(output_dir: Path):
    """Within the block, the driver's lines also go to ``output_dir/sweep.log`` (appended)."""
    log = console()
    output_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(output_dir / LOG_FILE, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    try:
        yield log
    finally:
        log.removeHandler(handler)
        handler.close()
