"""One sweep per output folder: an OS lock that a live holder keeps (a second launch is refused,
naming it) and that the kernel frees when its process dies (the next launch takes over, saying so)."""

import json
import os
import subprocess
import sys
import time

import pytest

from pipeline.experiment.lock import HOLDER_NAME, SweepLock, SweepLocked

HOLD = """
import sys, time
from pipeline.experiment.lock import SweepLock
held = SweepLock(sys.argv[1]).acquire()  # kept: a collected FileLock releases itself
print("held", flush=True)
time.sleep(120)
"""


def hold_in_another_process(folder):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_live_holder_refuses_a_second_lock_naming_its_pid_and_command(tmp_path):
    with SweepLock(tmp_path) as first:
        assert first.stale is None
        holder = json.loads((tmp_path / HOLDER_NAME).read_text())
        assert holder["pid"] == os.getpid() and holder["command"]
        with pytest.raises(SweepLocked, match=rf"output_dir {tmp_path} is held by a running sweep "
                                              rf"\(pid {os.getpid()} on .*, command: "):
            SweepLock(tmp_path).acquire()
    assert not (tmp_path / HOLDER_NAME).exists()  # a clean release leaves no note
    SweepLock(tmp_path).acquire().release()        # and the lock is free again


def test_the_kernel_frees_the_lock_of_a_killed_holder_and_the_next_launch_says_so(tmp_path):
    proc = hold_in_another_process(tmp_path)
    with pytest.raises(SweepLocked, match=rf"pid {proc.pid} "):
        SweepLock(tmp_path).acquire()  # its holder still runs
    proc.kill()
    proc.wait()
    start = time.monotonic()
    lock = SweepLock(tmp_path).acquire()  # no /proc heuristics: the lock itself is free
    assert time.monotonic() - start < 5
    assert lock.stale["pid"] == proc.pid
    assert json.loads((tmp_path / HOLDER_NAME).read_text())["pid"] == os.getpid()
    lock.release()


def test_an_unreadable_holder_note_is_stale_as_well(tmp_path):
    (tmp_path / HOLDER_NAME).write_text("not json")
    lock = SweepLock(tmp_path).acquire()
    assert lock.stale is not None
    lock.release()
