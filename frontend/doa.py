"""Direction of arrival by SRP-PHAT on the array's own geometry, vectorised over a spherical grid.

Input per event: each mic's whitened impulse response (see :mod:`frontend.timing`) time-gated around the
direct path, so reflections arriving later do not bias the direction. With the gated spectra ``G_m(f)``
(PHAT-normalised per mic) the steered response power is

    P(u) = Σ_f w_f |Σ_m G_m(f) exp(-j 2π f u·m_m / c)|²,

which peaks when ``u`` (unit vector in the array frame, toward the source) aligns the mics' pulses: a
plane wave from ``u`` reaches mic ``m`` ``u·m/c`` earlier than the origin. ``P`` is evaluated on a
spherical Fibonacci grid for all events at once (one batched complex matrix product per frequency,
steering matrix precomputed per array), then refined from the best grid point by a few rounds of a
quadratic fit on a shrinking tangent-plane stencil, to well below the grid step.

Normalised power ``(P / Σ_f w_f − M) / (M (M − 1))`` is 1 for one clean plane wave and near 0 for
diffuse noise: it is the ``quality`` column of doa.csv.
"""
from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from .timing import phasors


def fibonacci_sphere(n):
    """(n, 3) nearly uniform unit vectors (spherical Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.c_[r * np.cos(phi), r * np.sin(phi), z]


def is_planar(mics, tol=1e-3):
    """Unit normal of the mics' plane if they are (nearly) coplanar (spread < tol m), else None."""
    mics = np.asarray(mics, float)
    if len(mics) < 3:
        return None
    d = mics - mics.mean(axis=0)
    _, sv, vt = np.linalg.svd(d)
    return vt[2] if sv[2] / np.sqrt(len(mics)) < tol else None


_SETUP_CACHE = {}


def srp_setup(mics, freqs, c, step_deg=3.0, hemisphere=None, n_grid_freqs=16):
    """Precompute the grid search for one array (cached: arrays of one model share it).

    mics : (M, 3) positions in the array frame (m). freqs : (F,) Hz of the gated spectra.
    step_deg : mean spacing of the grid. hemisphere : (3,) unit axis or None.
    n_grid_freqs : frequencies used by the grid search (spread over the band; the main lobe of a
        few-cm array is tens of degrees wide, so a coarse search cannot miss it); the refinement uses all.

    Returns a dict: grid (G, 3), steer (F', G, M) complex64, fidx (F',) indices into freqs, mics, freqs,
    c, hemisphere, step (rad), planar_normal, mirror (bool: planar array with a hemisphere, so the
    mirror image across the plane is equivalent).
    """
    mics = np.asarray(mics, float)
    hemi = None if hemisphere is None else np.asarray(hemisphere, float)
    key = (mics.tobytes(), np.asarray(freqs, float).tobytes(), float(c), float(step_deg),
           None if hemi is None else hemi.tobytes(), int(n_grid_freqs))
    if key in _SETUP_CACHE:
        return _SETUP_CACHE[key]
    step = np.deg2rad(step_deg)
    grid = fibonacci_sphere(int(np.ceil(4 * np.pi / step**2)))
    if hemi is not None:
        grid = grid[grid @ hemi >= -0.5 * step]
    fidx = np.unique(np.linspace(0, len(freqs) - 1, min(n_grid_freqs, len(freqs))).round().astype(int))
    delays = grid @ mics.T / c  # (G, M): lead of each mic over the origin
    steer = np.exp(-2j * np.pi * freqs[fidx, None, None] * delays[None]).astype(np.complex64)
    normal = is_planar(mics)
    mirror = hemi is not None and normal is not None and abs(normal @ hemi) > 0.5
    out = {"grid": grid, "steer": steer, "fidx": fidx, "mics": mics, "freqs": np.asarray(freqs, float),
           "c": c, "hemisphere": hemi, "step": step, "mirror": mirror, "planar_normal": normal}
    if len(_SETUP_CACHE) > 8:
        _SETUP_CACHE.clear()
    _SETUP_CACHE[key] = out
    return out


def srp_power(g, mics, freqs, c, u, weights=None):
    """Exact normalised SRP at directions u.

    g : (J, M, F) PHAT-normalised gated spectra. u : (J, K, 3). Returns (J, K).
    """
    weights = np.ones(len(freqs)) if weights is None else weights
    delays = u @ mics.T / c  # (J, K, M)
    ph = phasors(freqs, -delays)  # (J, K, M, F)
    y = np.einsum("jkmf,jmf->jkf", ph, g)
    return _normalise((np.abs(y) ** 2 * weights).sum(-1), weights.sum(), len(mics))


def _normalise(p, wsum, m):
    return (p / wsum - m) / (m * (m - 1)) if m > 1 else p / wsum


def _tangent_basis(u):
    """Two unit vectors orthogonal to each u (..., 3)."""
    a = np.where(np.abs(u[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(u, e1)


def _fold(u, setup):
    """Keep directions in the hemisphere for planar arrays (their mirror image is equivalent)."""
    h = setup["hemisphere"]
    if setup["mirror"]:
        d = u @ h
        u = u - 2 * np.minimum(d, 0.0)[..., None] * h
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def srp_doa(g, setup, weights=None, refine_to_deg=0.02):
    """DOA of each event.

    g : (J, M, F) PHAT-normalised gated spectra (F matches setup["freqs"]).

    Returns
    -------
    u : (J, 3) unit vectors (array frame, toward the source).
    power : (J,) normalised SRP at u (1 = one clean plane wave).
    """
    j = g.shape[0]
    freqs, mics, c = setup["freqs"], setup["mics"], setup["c"]
    w = np.ones(len(freqs)) if weights is None else weights
    # grid search, all events at once, one (G, M) @ (M, J) product per frequency (a loop over F beats
    # numpy's batched matmul for these thin matrices)
    fidx = setup["fidx"]
    gt = np.transpose(g[:, :, fidx], (2, 1, 0)).astype(np.complex64)  # (F', M, J)
    p = np.zeros((len(setup["grid"]), j))
    # single-threaded BLAS: these thin products are ~10x slower with OpenBLAS threads on a busy machine
    with threadpool_limits(limits=1, user_api="blas"):
        for f in range(len(fidx)):
            y = setup["steer"][f] @ gt[f]
            p += w[fidx[f]] * (y.real**2 + y.imag**2)
    p = _normalise(p, w[fidx].sum(), len(mics))  # (G, J)
    u = setup["grid"][np.argmax(p, axis=0)].copy()

    # local refinement: 3x3 stencil in the tangent plane, quadratic fit, shrink
    h = 0.5 * setup["step"]  # the grid's best point is within about half a step of the peak
    s = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], float)  # (9, 2)
    design = np.c_[np.ones(9), s, s[:, 0] ** 2, s[:, 1] ** 2, s[:, 0] * s[:, 1]]
    pinv = np.linalg.pinv(design)
    while h > np.deg2rad(refine_to_deg):
        e1, e2 = _tangent_basis(u)
        pts = u[:, None, :] + h * (s[None, :, 0:1] * e1[:, None, :] + s[None, :, 1:2] * e2[:, None, :])
        pts /= np.linalg.norm(pts, axis=-1, keepdims=True)
        val = srp_power(g, mics, freqs, c, pts, w)  # (J, 9)
        coef = val @ pinv.T  # (J, 6): c0, bx, by, axx, ayy, axy
        hess = np.stack([np.stack([2 * coef[:, 3], coef[:, 5]], -1), np.stack([coef[:, 5], 2 * coef[:, 4]], -1)], -2)
        grad = coef[:, 1:3]
        neg_def = (np.linalg.det(hess) > 0) & (hess[:, 0, 0] < 0)
        delta = np.zeros((j, 2))
        if neg_def.any():
            delta[neg_def] = -np.linalg.solve(hess[neg_def], grad[neg_def][..., None])[..., 0]
        # outside the stencil or not a maximum: move to the best stencil point instead
        bad = ~neg_def | (np.abs(delta).max(axis=1) > 1.0)
        delta[bad] = s[np.argmax(val[bad], axis=1)]
        u = _fold(u + h * (delta[:, 0:1] * e1 + delta[:, 1:2] * e2), setup)
        h *= 0.7 if bad.all() else 0.5
    return u, srp_power(g, mics, freqs, c, u[:, None, :], w)[:, 0]
