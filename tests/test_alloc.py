"""calib.alloc: the CLI's allocator settings make freed large blocks reusable (glibc), and stand aside otherwise."""
from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# allocate, touch and free a 48 MiB array 20 times; print (keep_freed_memory's result, minor page faults)
PROBE = """
import resource, sys
import numpy as np
from calib.alloc import keep_freed_memory
ok = keep_freed_memory() if sys.argv[1] == "1" else None
a = np.ones(6 << 20); del a                       # the first one faults in any case
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    a = np.ones(6 << 20); del a                   # 48 MiB: above glibc's largest automatic mmap threshold
print(ok, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


def _probe(apply, env=None):
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}, **(env or {})}
    out = subprocess.run([sys.executable, "-c", PROBE, "1" if apply else "0"], capture_output=True, text=True,
                         env=env, check=True).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not GLIBC, reason="glibc's mallopt only")
def test_freed_blocks_are_reused_instead_of_faulted_in_again():
    ok, faults = _probe(True)
    _, faults_default = _probe(False)
    assert ok == "True"
    # by default each array is a fresh mapping, faulted in again (numpy asks for huge pages: fewer than one
    # fault per 4 KiB, but at least one per array); kept in the heap, the same pages are reused
    assert faults_default >= 20
    assert faults <= faults_default // 10


@pytest.mark.skipif(not GLIBC, reason="glibc's mallopt only")
def test_the_users_environment_settings_stand():
    ok, _ = _probe(True, env={"MALLOC_TRIM_THRESHOLD_": "131072"})
    assert ok == "False"


FEATURES = """
import pickle, sys
from calib.alloc import keep_freed_memory
from calib.pipeline.features import session_features
if sys.argv[2] == "1":
    keep_freed_memory()
feats, _ = session_features(sys.argv[1], jobs=2)
sys.stdout.buffer.write(pickle.dumps({k: feats[k] for k in ("events", "tdoa_m", "tdoa_s", "doa")}))
"""


def test_allocator_settings_do_not_change_the_features():
    # the heap's reuse moves arrays to other addresses (and alignments): the features stay bit-identical
    import pickle
    from pathlib import Path

    session = Path(__file__).resolve().parents[1] / "sample_data" / "lab3"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = [pickle.loads(subprocess.run([sys.executable, "-c", FEATURES, str(session), mode], capture_output=True,
                                       env=env, check=True).stdout) for mode in ("1", "0")]
    for key in out[0]:
        assert out[0][key].equals(out[1][key]), key
