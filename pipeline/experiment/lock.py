"""One sweep per output folder: an operating-system lock (``filelock``, flock on POSIX) that the
kernel frees when its process dies, however it dies, and a note naming the holder (host, pid,
command, since when) for the message a refused launch prints.

A second launch on a folder a running sweep holds is refused with the holder named; a folder
whose lock is free but whose holder note was left behind (a killed driver) is taken over, and the
launch says so (``stale``), so it can close what that driver left open.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path

from filelock import FileLock, Timeout

LOCK_NAME = ".sweep.lock"           # the OS lock
HOLDER_NAME = ".sweep.holder.json"  # who holds it (removed on a clean release)


class SweepLocked(RuntimeError):
    """The output folder is held by a sweep that is still running."""


class SweepLock:
    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.holder_path = self.folder / HOLDER_NAME
        self.stale: dict | None = None  # the note of a killed holder this lock replaced
        self._lock = FileLock(str(self.path), timeout=0)

    def acquire(self) -> "SweepLock":
        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire()
        except Timeout:
            holder = self._holder() or {}
            raise SweepLocked(
                f"output_dir {self.folder} is held by a running sweep (pid {holder.get('pid', '?')} on "
                f"{holder.get('host', '?')}, since {holder.get('since', '?')}, command: "
                f"{holder.get('command', '?')}): wait for it, stop it, or pass another output_dir") from None
        self.stale = self._holder()  # a note without a live lock: its driver was killed
        me = {"host": socket.gethostname(), "pid": os.getpid(), "since": time.strftime("%Y-%m-%d %H:%M:%S"),
              "command": " ".join(sys.argv)}
        self.holder_path.write_text(json.dumps(me))
        return self

    def _holder(self) -> dict | None:
        try:
            return json.loads(self.holder_path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {"pid": "?", "since": "?", "note": "unreadable holder note"}

    def release(self) -> None:
        if self._lock.is_locked:
            self.holder_path.unlink(missing_ok=True)
            self._lock.release()

    def __enter__(self) -> "SweepLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
