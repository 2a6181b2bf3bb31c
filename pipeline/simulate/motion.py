"""A speaker that moves while it chirps: time-varying propagation and Doppler, for the room simulator.

The robot's path is a scenario key ``trajectory = {t: (n,) s on the emitter clock, pos: (n, 3) m, room
frame}``, interpolated by a cubic spline (:class:`Trajectory`). A chirp is emitted from ``s(t)`` at every
instant ``t`` of the sweep. At a mic ``r`` a path (direct or image ``k``, ``p_k(s) = M_k s + b_k``) received
at true time ``T`` was emitted at the time ``t_e`` solving

    T = t_e + |p_k(s(t_e)) − r| / c                          (the retarded time; fixed point, |v|/c ≪ 1)

and contributes ``A_k(t_e) x(t_e − t_start) / |p_k(s(t_e)) − r|``: the chirp evaluated analytically at the
emission time. This is the exact time-varying delay (Doppler compression, the range–Doppler coupling of a
matched filter, changing spreading) with no interpolation error. Paths within ``MOVING_EARLY`` of the
direct path are rendered this way, with their band amplitudes (walls, directivity, air) taken at the
middle of the sweep and their visibility (walls of a non-convex room, obstacles) interpolated between
``N_VIS_KNOTS`` instants of the sweep, so a path that is cut by a corner fades out as the robot passes it.
Later images and the stochastic tail come from the RIR at the middle of the sweep (their Doppler, < 0.2 %
of a frequency, is neglected).

Truth convention: an event's time is the sweep START ``t_emit[j]`` and its source position is
``s(t_emit[j])`` (docs/architecture.md: "arrival at the chirp's start").
"""
from __future__ import annotations

import math

import numpy as np
from scipy.fft import irfft, next_fast_len, rfft, rfftfreq

from calib.pipeline.simulate import acoustics as ac
from calib.pipeline.simulate import clocks

MOVING_EARLY = 0.02   # s after the direct path: paths rendered with the exact time-varying delay
N_VIS_KNOTS = 5       # instants of the sweep at which a moving source's path visibility is evaluated
GRID_STEP = 1e-3      # s: the spline is tabulated this finely for the retarded-time iterations
N_ITER = 3            # fixed-point iterations of the retarded time (error shrinks by |v|/c each)
COARSE = 16           # samples between exact retarded-time solutions (linear interpolation in between:
                      # error ≈ (a/c) h² / 8 < 1e-9 s for h = 1 ms and any robot acceleration a < 10 m/s²)
MARGIN = 8            # samples around the early part


class Trajectory:
    """s(t) of a moving speaker: cubic spline through ``t`` (n,) s, ``pos`` (n, 3) m."""

    def __init__(self, spec):
        from scipy.interpolate import CubicSpline

        self.t = np.asarray(spec["t"], float)
        self.pos = np.asarray(spec["pos"], float)
        self.spline = CubicSpline(self.t, self.pos, axis=0)

    def __call__(self, t):
        return self.spline(np.asarray(t, float))

    def velocity(self, t):
        return self.spline(np.asarray(t, float), 1)

    def table(self, lo, hi):
        """(grid (n,), positions (n, 3)) tabulated every GRID_STEP over [lo, hi]."""
        g = np.arange(lo, hi + GRID_STEP, GRID_STEP)
        return g, self(g)


def early_mask(paths, fsp):
    """(n,) bool: images whose earliest geometric arrival at the array (blocked or not: the speaker moves,
    visibility may change during the sweep) is within MOVING_EARLY of the direct path."""
    taps = paths["taps_open"]
    rel = np.min(np.where(np.isfinite(taps), taps, np.inf), axis=1) - paths["first"]
    return rel <= MOVING_EARLY * fsp


def early_part(e, a, paths, sel, sc, t0, level, vis_gain=None):
    """The moving emitter ``e``'s early paths ``sel`` at array ``a``: (first sample, (M, n) samples) on
    the array's sample grid (its nominal rate ``a['fs']``, its clock: drifting, and with its faults —
    dropped or inserted blocks, drift terms, a wrong rate — when it has them, as :func:`render.segment`).

    paths : :func:`render.band_paths` at the middle of the sweep; vis_gain : optional function(times (k,))
    → (k, n_img, M, B) path gains at those emission times (polygonal rooms), else the middle's gains.
    """
    fs, c, traj = a["fs"], sc["speed_of_sound"], e["trajectory"]
    t_s, dur = e["t_start"], e["dur"]
    fsp = fs * clocks.rate(a, t_s)
    mics = a["mics_room"]
    idx = np.flatnonzero(sel)               # never empty: the direct path is always selected
    d = paths["dist"][idx]
    lo = int(math.floor(fs * clocks.local(a, t_s + np.nanmin(d) / c - 0.01, t0))) - MARGIN
    hi = int(math.ceil(fs * clocks.local(a, t_s + dur + np.nanmax(d) / c + 0.01, t0))) + MARGIN
    n_out = np.arange(lo, hi)
    T = clocks.true_time(a, n_out / fs, t0)                       # true receive time of each sample
    grid, table = traj.table(t_s - 0.1, t_s + dur + 0.1)
    s_mid = e["pos"]
    knots = t_s + dur * np.linspace(0, 1, N_VIS_KNOTS)
    g_knots = vis_gain(knots)[:, idx] if vis_gain is not None else None      # (k, n_sel, M, B)
    B = paths["amp"].shape[2]
    y = np.zeros((B, len(mics), n_out.size))
    m_ix = np.arange(len(mics))[:, None]
    coarse = T[::COARSE]                    # the retarded time is smooth: solved every COARSE samples
    if coarse[-1] != T[-1]:
        coarse = np.r_[coarse, T[-1]]
    for j, k in enumerate(idx):
        pk, Mk = e["images"]["pos"][k], e["images"]["M"][k]
        te = coarse[None, :] - np.linalg.norm(pk - mics, axis=1)[:, None] / c
        for _ in range(N_ITER):
            s = np.stack([np.interp(te, grid, table[:, q]) for q in range(3)], axis=-1)   # (M, n', 3)
            dist = np.sqrt(np.sum((pk + (s - s_mid) @ Mk.T - mics[:, None, :]) ** 2, axis=2))
            te = coarse[None, :] - dist / c
        dist = np.stack([np.interp(T, coarse, x) for x in dist])           # (M, n): smooth, interpolated
        te = T[None, :] - dist / c
        base = level * e["wave"](te - t_s) / dist                          # (M, n)
        if g_knots is None:
            y += paths["amp"][k].T[:, :, None] * base[None]
            continue
        gk = g_knots[:, j] * paths["amp_open"][k][None]                   # (knots, M, B)
        if np.all(gk == gk[:1]):
            y += gk[0].T[:, :, None] * base[None]
            continue
        w = np.clip((te - t_s) / dur * (N_VIS_KNOTS - 1), 0, N_VIS_KNOTS - 1 - 1e-9)   # visibility changes
        i0 = w.astype(int)
        f = w - i0
        for b in range(B):
            y[b] += (gk[i0, m_ix, b] * (1 - f) + gk[i0 + 1, m_ix, b] * f) * base
    return lo, _band_sum(y, fsp)


def _band_sum(y, fsp):
    """Σ_b w_b ⊛ y_b: the zero-phase octave crossover applied per band and summed (M, n)."""
    n = y.shape[2]
    nfft = next_fast_len(n + int(0.02 * fsp))
    W = ac.band_weights(rfftfreq(nfft, 1 / fsp))
    H = np.einsum("bf,bmf->mf", W, rfft(y, nfft, axis=2))
    return irfft(H, nfft, axis=1)[:, :n]
