"""One array's frontend result: what ``extract.time_array`` measured, read by the session-wide checks, the
feature tables and the diagnostics (``extract``)."""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from calib.records import Record


@dataclasses.dataclass(frozen=True, eq=False)
class ArrayResult(Record):
    """One array's detections, association, timing and DOAs (J matched events, M mics, D detections, K
    events in the session; times in s on the array's own clock).

    name : the array's name. fs : its sample rate (Hz). n_samples : recording length (samples). channels : M.
    phase : carrier phase (rad), one or (J,) (each event's own).
    env, env_rate : the detection plot's envelope (``diagnostics.envelope_summary``: t, y, median) and the
    full envelope's rate (Hz). det_t, det_score : (D,) detection times and peak / local background.
    assoc : ``associate.associate``'s dict (offset s, scale, det_of (K,), event_of (D,), n_matched, ...).
    ev_idx : (J,) int, the matched events' indices in the session's events.
    arrival : (J,) arrival at the array origin (timed against the Doppler bank's stretch ε̂: + β ε̂ once β is
    known). spread, mic_sd, arrival_sd : (J,) s, the fused arrival's standard error, one mic's spread, the
    claimed arrival error (``frontend.noise``). quality : (J,) in [0, 1]. flags : J lists of doubts.
    doa_spread : (J,) rad, each DOA's own spread (std of cos θ for a linear array). u : (J, 3) unit DOA, array
    frame (zeros without a DOA). doa_power : (J,) SRP power.
    redetected : (K,) bool. stretch : (J,) ε̂ (0 for a source at rest). ambiguous_plane : (3,) mic-plane
    normal of a planar array without a hemisphere, else None. has_doa : whether the geometry gives DOAs.
    doa_axis : (3,) a linear array's axis (its DOAs are cones about it), else None. warnings : list of str.
    timings : {stage: s}.
    late : (J,) s late against the array's range track (NaN: not judged; ``extract.flag_nlos``), None
    before that check. track_drift : that track's clock drift δ (NaN: not judged), None before that check.

    Frozen (a changed copy: :meth:`replace`); reads like the dict of earlier versions (``r["arrival"]``,
    ``r.get``; a field that is None is not a key). flags, quality and warnings are filled in place by the
    session-wide checks.
    """
    name: str
    fs: int
    n_samples: int
    channels: int
    phase: Any
    env: tuple
    env_rate: float
    det_t: np.ndarray
    det_score: np.ndarray
    assoc: dict
    ev_idx: np.ndarray
    arrival: np.ndarray
    spread: np.ndarray
    mic_sd: np.ndarray
    arrival_sd: np.ndarray
    quality: np.ndarray
    flags: list
    doa_spread: np.ndarray
    u: np.ndarray
    doa_power: np.ndarray
    redetected: np.ndarray
    stretch: np.ndarray
    ambiguous_plane: np.ndarray | None
    has_doa: bool
    doa_axis: np.ndarray | None
    warnings: list
    timings: dict
    late: np.ndarray | None = None
    track_drift: float | None = None
