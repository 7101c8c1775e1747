"""One sweep per output folder: a live holder refuses a second launch, a dead one is stale."""

import json
import os
import subprocess
import sys

import pytest

from pipeline.experiment.lock import LOCK_NAME, SweepLock, SweepLocked


def test_a_live_holder_refuses_a_second_lock_and_releases_on_exit(tmp_path):
    with SweepLock(tmp_path) as first:
        assert first.stale is None and (tmp_path / LOCK_NAME).exists()
        holder = json.loads((tmp_path / LOCK_NAME).read_text())
        assert holder["pid"] == os.getpid()
        with pytest.raises(SweepLocked, match=rf"output_dir {tmp_path} is held by a running sweep \(pid {os.getpid()}"):
            SweepLock(tmp_path).acquire()
    assert not (tmp_path / LOCK_NAME).exists()


def test_a_lock_left_by_a_killed_process_is_stale_and_taken_over(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    (tmp_path / LOCK_NAME).write_text(json.dumps({"host": os.uname().nodename, "pid": proc.pid,
                                                  "started": None, "since": "then"}))
    with pytest.raises(SweepLocked):
        SweepLock(tmp_path).acquire()  # its holder still runs
    proc.kill()
    proc.wait()
    lock = SweepLock(tmp_path).acquire()
    assert lock.stale["pid"] == proc.pid and json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    lock.release()


def test_a_reused_pid_is_not_mistaken_for_the_holder(tmp_path):
    """Our own pid with another process start time: the holder is gone, the pid was reused."""
    (tmp_path / LOCK_NAME).write_text(json.dumps({"host": os.uname().nodename, "pid": os.getpid(),
                                                  "started": "1", "since": "then"}))
    lock = SweepLock(tmp_path).acquire()
    assert lock.stale is not None
    lock.release()
    (tmp_path / LOCK_NAME).write_text("not json")  # unreadable: stale as well
    SweepLock(tmp_path).acquire().release()
