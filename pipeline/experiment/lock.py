"""One sweep per output folder: a lock file naming the holder (host, pid, process start time).

A second launch on a folder a running sweep holds is refused; a lock left by a killed sweep is
stale (its process is gone, or the pid now belongs to another process) and is taken over.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

LOCK_NAME = ".sweep.lock"


class SweepLocked(RuntimeError):
    """The output folder is held by a sweep that is still running."""


def _start_time(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux /proc), None elsewhere."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _alive(holder: dict) -> bool:
    if holder.get("host") != socket.gethostname():
        return True  # another machine's process cannot be checked: assume it runs
    pid = int(holder.get("pid", -1))
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    started = _start_time(pid)
    return started is None or holder.get("started") in (None, started)


class SweepLock:
    def __init__(self, folder: str | Path):
        self.path = Path(folder) / LOCK_NAME
        self.stale: dict | None = None  # the holder of a stale lock this one replaced

    def acquire(self) -> "SweepLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        me = {"host": socket.gethostname(), "pid": os.getpid(), "started": _start_time(os.getpid()),
              "since": time.strftime("%Y-%m-%d %H:%M:%S")}
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                holder = self._holder()
                if holder is not None and _alive(holder):
                    raise SweepLocked(
                        f"output_dir {self.path.parent} is held by a running sweep (pid {holder.get('pid')} "
                        f"on {holder.get('host')}, since {holder.get('since')}): wait for it, stop it, or "
                        f"pass another output_dir") from None
                self.stale = holder
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            return self
        raise SweepLocked(f"{self.path}: could not take the lock (another sweep took it at the same time)")

    def _holder(self) -> dict | None:
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None  # unreadable: treat as stale

    def release(self) -> None:
        holder = self._holder()
        if holder is not None and holder.get("pid") == os.getpid():
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> "SweepLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
