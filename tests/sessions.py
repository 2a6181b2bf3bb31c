"""Small recorded sessions from the room simulator, shared by the tests that need real WAVs."""
from __future__ import annotations

from calib.pipeline.simulate.roomsim import make_scenario, simulate

SHORT_CHIRP = {"duration": 0.2}  # s: keeps the WAVs (and the tests) small
EVENT_INTERVAL = 0.8             # s between chirps


def small_lab3_session(folder, seed, n_events, rt60, snr=30):
    """Simulate the ``lab3`` preset with ``n_events`` short chirps into ``folder``; returns ``folder``."""
    simulate(make_scenario("lab3", seed, n_events=n_events, interval=EVENT_INTERVAL, chirp=SHORT_CHIRP,
                           rt60=rt60, snr=snr), folder)
    return folder
