"""Run a command the way a user does (a fresh process) and measure it: wall time, CPU time, peak memory.

    from cliproc import measure, calib_cmd, load
    m = measure(calib_cmd("estimate", "features", "-o", "calibration", "-q"))
    m["wall_s"], m["cpu_s"], m["peak_mb"], m["rc"]

``os.wait4`` gives the child's own resource usage (user + system CPU, peak resident set ``ru_maxrss``),
not the whole machine's: on a shared machine the CPU time is the figure to compare (wall time grows with
the load; ``load()`` says how loaded the machine was).
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path


def calib_cmd(*args):
    """The ``calib`` command of this interpreter's environment, with ``args``."""
    exe = Path(sys.executable).with_name("calib")
    return [str(exe), *map(str, args)] if exe.exists() else [sys.executable, "-m", "calib", *map(str, args)]


def measure(cmd, *, env=None, cwd=None):
    """Run ``cmd`` to completion. Returns dict: rc, wall_s, user_s, sys_s, cpu_s, peak_mb, stdout, stderr
    (stdout/stderr as text, from files so a chatty child cannot block)."""
    import tempfile

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env, cwd=cwd)
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text_out, text_err = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    return {"rc": proc.returncode, "wall_s": wall, "user_s": ru.ru_utime, "sys_s": ru.ru_stime,
            "cpu_s": ru.ru_utime + ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024.0, "stdout": text_out,
            "stderr": text_err}


def load():
    """The 1-minute load average and the core count, as text for a benchmark's header."""
    return f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"
