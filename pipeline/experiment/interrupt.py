"""Stopping a sweep on SIGINT (Ctrl-C) or SIGTERM: the driver's handlers raise ``SweepInterrupted``
in the main thread; the executor cancels what is running, the sweep marks interrupted runs KILLED
and exits with 128 + the signal number. Finished jobs are already recorded; interrupted ones resume
from their last round checkpoint on the next launch.
"""

from __future__ import annotations

import contextlib
import signal
import threading

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class SweepInterrupted(BaseException):
    """Raised in the driver's main thread by a stop signal (not an ``Exception``: nothing that
    catches job errors may swallow it)."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


_STATE = {"depth": 0, "pending": None}  # critical-section depth (main thread), a deferred signal


def _raise(signum, frame) -> None:
    if _STATE["depth"]:  # inside bookkeeping (an MLflow write, a records file): finish it first
        _STATE["pending"] = signum
        return
    raise SweepInterrupted(signum)


@contextlib.contextmanager
def critical():
    """Bookkeeping that a stop signal must not cut in half (a half-done SQLite transaction keeps
    the tracking store locked): the signal is raised when the outermost section ends."""
    _STATE["depth"] += 1
    try:
        yield
    finally:
        _STATE["depth"] -= 1
        if _STATE["depth"] == 0 and _STATE["pending"] is not None:
            signum, _STATE["pending"] = _STATE["pending"], None
            raise SweepInterrupted(signum)


def install_stop_handlers() -> None:
    """(Re)install the handlers: Ray installs its own SIGTERM handler when it starts, so the
    executor calls this again after ``ray.init``. Only the main thread can. ``current_handlers``
    before and ``restore_handlers`` after give the caller's back."""
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, _raise)


def current_handlers() -> dict:
    return {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}


def restore_handlers(previous: dict) -> None:
    if threading.current_thread() is not threading.main_thread():
        return
    for sig, handler in previous.items():
        if handler is not None:
            signal.signal(sig, handler)


def ignore_stop_signals() -> None:
    """While the driver cleans up after a stop, a second Ctrl-C must not cut the cleanup short."""
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)
