"""Shared by every test file: each test runs on one torch thread; `lock_held_elsewhere`."""

import contextlib
import os
import signal
import subprocess
import sys

import pytest
import torch


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny models gain nothing from threads, and two threads on a busy 2-core machine can run
    10x slower."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def lock_held_elsewhere():
    """hold(folder, command): a context in which another process holds runs.folder_lock(folder,
    command) (yields that process); leaving it kills the holder (SIGKILL), as a crashed run."""

    @contextlib.contextmanager
    def hold(folder, command):
        holder = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import sys, time, runs\nwith runs.folder_lock(sys.argv[1], sys.argv[2]):\n "
                "print('held', flush=True); time.sleep(60)",
                str(folder),
                command,
            ],
            cwd=os.path.dirname(os.path.abspath(__file__)),
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert holder.stdout.readline().strip() == "held"
            yield holder
        finally:
            holder.send_signal(signal.SIGKILL)
            holder.wait()

    return hold
