"""The scene presets of ``calib simulate`` (plain data: the CLI lists them without loading the simulator).

Each preset is a dict of scenario keys that :func:`calib.pipeline.simulate.scenario.make_scenario` applies
over its defaults; docs/simulation.md describes them.
"""
from __future__ import annotations

from typing import Any

PRESETS: dict[str, dict[str, Any]] = {
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
REALISTIC = ("lab", "hall", "hard", "occluded-lab")

# Deployment presets (issue 27; layouts in deploy.py). "draws": keys drawn per seed, U(lo, hi), unless given.
_LAB = {**_REAL, "n_arrays": 4, "room_dim": [6.0, 5.0, 3.0], "fs": 16000, "interval": 2.0,
        "draws": {"rt60": [0.35, 0.55]}}
PRESETS |= {
    # the four scenes of issue 27
    "occluded-lab": {**PRESETS["hard"], "fs": 44100, "draws": {"occlusion_db": [10.0, 20.0], "rt60": [0.35, 0.5]}},
    "office": {**_LAB, "room_shape": "L", "n_arrays": 5, "mounts": ["wall", "table", "wall", "wall", "stand"],
               "boards": ["circle7c", "circle6", "linear4", "tetra", "pair"], "n_stops": 20, "n_speech": 1,
               "draws": {"rt60": [0.4, 0.65]}},
    "robot": {**_LAB, "room_dim": [10.0, 8.0, 3.0], "n_arrays": 5, "motion": "any", "n_stops": 64, "interval": 3.0,
              "boards": ["circle6", "circle6", "tetra@16000", "circle6", "circle7c@16000"],
              "mounts": ["wall", "table", "stand", "wall", "table"], "draws": {"rt60": [0.45, 0.55]}},
    "warehouse": {**_REAL, "room_dim": [20.0, 15.0, 6.0], "fs": 16000, "snr": 5.0, "diffuse_snr": 15.0,
                  "n_arrays": 10, "n_stops": 16, "interval": 2.5, "heights": [1.5, 1.1],
                  "boards": ["circle6", "circle6", "tetra@16000"], "mounts": ["wall", "table", "wall", "stand"],
                  "n_obstacles": 2, "obstacle_loss_db": [6.0, 14.0], "n_noise": 1,
                  "draws": {"rt60": [1.1, 1.3], "n_arrays": [10, 12]}},
    # one condition each
    "lshape": {**_LAB, "room_shape": "L", "mounts": ["wall", "table", "wall", "wall"], "draws": {"rt60": [0.4, 0.6]}},
    "ushape": {**_LAB, "room_shape": "U", "n_arrays": 5, "mounts": ["wall", "table", "wall", "wall", "stand"],
               "draws": {"rt60": [0.45, 0.65]}},
    "moving": {**_LAB, "room_dim": [8.0, 6.0, 3.0], "motion": "any", "n_stops": 20, "interval": 3.0},
    "mixed": {**_LAB, "room_dim": [7.0, 6.0, 3.0], "n_arrays": 5,
              "boards": ["circle7c", "circle6", "linear4", "tetra", "pair"],
              "mounts": ["wall", "table", "wall", "stand", "wall"]},
    "talkers": {**_LAB, "n_speech": 2, "n_noise": 1, "n_interferers": 1, "talker_overlap": True},
    "occluded": {**_LAB, "room_dim": [7.0, 5.0, 3.0], "n_obstacles": 2},
    "bighall": {**_REAL, "room_dim": [20.0, 15.0, 6.0], "fs": 16000, "snr": 5.0, "diffuse_snr": 15.0,
                "n_stops": 16, "interval": 2.5, "heights": [1.5, 1.1], "boards": ["circle6", "circle6", "tetra@16000"],
                "mounts": ["wall", "table", "wall", "stand"], "draws": {"rt60": [1.1, 1.3], "n_arrays": [10, 12]}},
    # everything at once
    "deploy": {**_LAB, "room_shape": "nonconvex", "n_arrays": 5, "motion": "any", "n_stops": 30, "interval": 3.0,
               "boards": ["circle7c", "circle6", "linear4", "tetra", "pair"],
               "mounts": ["wall", "table", "wall", "stand", "wall"], "n_speech": 1, "n_noise": 1, "n_obstacles": 1},
}
DEPLOY = ("office", "robot", "warehouse", "lshape", "ushape", "moving", "mixed", "talkers", "occluded", "bighall",
          "deploy")
ISSUE27_SCENES = ("occluded-lab", "office", "robot", "warehouse")
