"""The scene presets of ``calib simulate`` (plain data: the CLI lists them without loading the simulator).

Each preset is a dict of scenario keys that :func:`calib.pipeline.simulate.scenario.make_scenario` applies
over its defaults; docs/simulation.md describes them.
"""
from __future__ import annotations

PRESETS = {
    "paper-traj1": {"n_arrays": 5, "room_margin": 1.5},
    "paper-traj2": {"n_arrays": 5, "room_margin": 1.5},
    "paper-traj3": {"n_arrays": 5, "room_margin": 1.5},
    "lab3": {"n_arrays": 3, "room_dim": [6.0, 5.0, 3.0], "tilt_deg": 3.0},
}
# Realistic presets (model "bands"): see docs/simulation.md "Realistic acoustics".
_REAL = {"model": "bands", "directivity": "cardioid", "snr": 40.0, "diffuse_snr": 20.0, "hum_snr": 30.0,
         "gain_mismatch_db": 2.0}
PRESETS |= {
    "lab": {**_REAL, "n_arrays": 4, "room_dim": [6.0, 5.0, 3.0], "rt60": 0.4, "fs": 16000, "interval": 1.5},
    "hall": {**_REAL, "n_arrays": 6, "room_dim": [12.0, 8.0, 4.0], "rt60": 0.8, "fs": 48000, "interval": 2.0,
             "chirp": {"f0": 500.0, "f1": 10000.0}},
    "hard": {**_REAL, "n_arrays": 4, "room_dim": [6.0, 5.0, 3.0], "rt60": 0.4, "fs": 16000, "interval": 1.5,
             "n_occluded": 1, "n_speech": 1, "n_quiet": 1},
}
REALISTIC = ("lab", "hall", "hard")
