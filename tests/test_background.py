"""pipeline.background: a function's value, its exception, and a second process that dies."""
import os
import signal

import pytest

from calib.pipeline.background import Background


def _square(x):
    return x * x


def _fail(msg):
    raise ValueError(msg)


def _die_in_child(parent):
    if os.getpid() != parent:   # in the second process: killed before it answers
        os.kill(os.getpid(), signal.SIGKILL)
    return "done here"


def test_value_and_exception():
    with Background(_square, 7) as job:
        assert job.result() == 49
    with Background(_fail, "bad input") as job, pytest.raises(ValueError, match="bad input"):
        job.result()


def test_a_dead_second_process_means_the_work_is_done_here():
    with Background(_die_in_child, os.getpid()) as job:
        assert job.result() == "done here"


def test_leaving_early_ends_the_second_process():
    job = Background(_square, 3)
    with job:
        pass   # result never asked for (an error in the main work)
    assert job.proc is None


def test_ended_mid_send_under_calibs_signal_handlers_prints_nothing():
    """`calib estimate` installs handlers that turn SIGTERM into an exception; a forked second process ended by
    close() while it sends a result nobody reads (larger than the pipe) must die quietly, not print a
    traceback the user sees."""
    import subprocess
    import sys
    script = ("import time\nfrom calib.cli import signals\nsignals.install()\n"
              "from calib.pipeline.background import Background\n"
              "def big():\n    return b'x' * 10_000_000\n"
              "with Background(big):\n    time.sleep(1.0)\nprint('done')\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout == "done\n" and r.stderr == "", r.stderr
