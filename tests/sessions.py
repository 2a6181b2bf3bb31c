"""Small recorded sessions from the room simulator, shared by the tests that need real WAVs."""
from __future__ import annotations

import os
from pathlib import Path

from calib.pipeline.simulate.roomsim import make_scenario, simulate

# calibrate() options for the model-fit verdict alone: tests of other mechanisms on scenes at the paper's noise
# (arrays several cm off, as their std says) would otherwise see those arrays named as short of the precision target
NO_TARGET = {"target_position": 0.0, "target_orientation_deg": 0.0}

# The paper lab's real feature sets: $CALIB_REAL_WORLD, else ../shared/real_world beside the checkout
# (benchmarks/realdata.py looks in the same places); tests that need them skip when they are absent.
REAL_WORLD = Path(os.environ.get("CALIB_REAL_WORLD") or Path(__file__).resolve().parents[2] / "shared" / "real_world")

SHORT_CHIRP = {"duration": 0.2}  # s: keeps the WAVs (and the tests) small
EVENT_INTERVAL = 0.8             # s between chirps


def small_lab3_session(folder, seed, n_events, rt60, snr=30):
    """Simulate the ``lab3`` preset with ``n_events`` short chirps into ``folder``; returns ``folder``."""
    simulate(make_scenario("lab3", seed, n_events=n_events, interval=EVENT_INTERVAL, chirp=SHORT_CHIRP,
                           rt60=rt60, snr=snr), folder)
    return folder


def read_array_audio(array):
    """One array's whole recording (short test files): ((M, N) float32, fs), read as the frontend reads it."""
    from calib.frontend.signals import ArrayAudio

    with ArrayAudio(array) as audio:
        return audio[:, 0 : audio.frames], audio.fs
