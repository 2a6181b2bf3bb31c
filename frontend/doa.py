"""Direction of arrival by SRP-PHAT on the array's own geometry, vectorised over a spherical grid.

Input per event: each mic's whitened impulse response (see :mod:`frontend.timing`) time-gated around the
direct path, so reflections arriving later do not bias the direction. With the gated spectra ``G_m(f)``
(PHAT-normalised per mic) the steered response power is

    P(u) = Σ_f w_f |Σ_m G_m(f) exp(-j 2π f u·m_m / c)|²,

which peaks when ``u`` (unit vector in the array frame, toward the source) aligns the mics' pulses: a
plane wave from ``u`` reaches mic ``m`` ``u·m/c`` earlier than the origin. ``P`` is evaluated on a
spherical Fibonacci grid for all events at once (one batched complex matrix product per frequency,
steering matrix precomputed per array), then refined from the best grid point by a few rounds of a
quadratic fit on a shrinking tangent-plane stencil, to well below the grid step (planar arrays: in the mic
plane, where their SRP lives, :func:`_refine_planar`). :func:`band_scatter` states each DOA's error from the
disagreement of sub-bands (a reflection the gate cannot separate).

Normalised power ``(P / Σ_f w_f − M) / (M (M − 1))`` is 1 for one clean plane wave and near 0 for
diffuse noise: it is the ``quality`` column of doa.csv.

What an array can measure depends on its geometry (:func:`mic_geometry`): a 3-D array the full direction,
a planar one the direction up to its mirror image across the mic plane (unless a hemisphere is stated), a
linear array or a 2-mic pair only the angle θ between its axis ``a`` and the source (``u·m`` is then
``u·c₀ + d_m cos θ`` for mics ``c₀ + d_m a``, the first term common to all mics: ``P`` depends on θ alone,
searched on a 1-D grid by :func:`srp_cone`), a single microphone nothing.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from calib.blas import single_thread_blas
from calib.geometry import fold, mic_geometry, mirror  # (mic_geometry: this module's public name too)

from .timing import phasors


def fibonacci_sphere(n):
    """(n, 3) nearly uniform unit vectors (spherical Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.c_[r * np.cos(phi), r * np.sin(phi), z]


def cone_vectors(axis, cos_theta):
    """Unit vectors (J, 3) at angle arccos(cos_theta) (J,) from ``axis``: the doa.csv rows of a linear
    array (any vector on the cone; this one lies in the plane of the axis and a fixed perpendicular)."""
    a = np.asarray(axis, float)
    e = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
    e /= np.linalg.norm(e)
    c = np.clip(np.asarray(cos_theta, float), -1.0, 1.0)
    return c[:, None] * a + np.sqrt(1.0 - c * c)[:, None] * e


def srp_cone(g, mics, axis, freqs, c, weights=None, step_deg=1.0, refine_to_deg=0.01):
    """Angle to the axis of a linear array (2-mic pair) by SRP-PHAT over θ ∈ [0°, 180°].

    g : (J, M, F) PHAT-normalised gated spectra. A grid of ``step_deg`` (finer than the main lobe of any
    array a few wavelengths long), then parabolic refinement on a shrinking 3-point stencil, down to
    ``refine_to_deg``, a row done sooner after two fitted steps in a row that short (:func:`_short_step`).
    Returns cos θ (J,) and the normalised power at θ (J,).
    """
    w = np.ones(len(freqs)) if weights is None else weights
    j = g.shape[0]
    theta = np.linspace(0.0, np.pi, int(np.ceil(180.0 / step_deg)) + 1)

    def power(t, rows=slice(None)):  # t (J, K) angles of the events ``rows`` → (J, K) normalised power
        u = cone_vectors(axis, np.cos(t).ravel()).reshape(*t.shape, 3)
        return srp_power(g[rows], mics, freqs, c, u, w)

    with single_thread_blas():
        p = power(np.broadcast_to(theta, (j, len(theta))))
    t = theta[np.argmax(p, axis=1)]
    h, tol = theta[1] - theta[0], np.deg2rad(refine_to_deg)
    act, was_short = np.arange(j), np.zeros(j, bool)   # the rows still refined (:func:`_short_step`)
    while h > tol and act.size:
        pts = np.clip(t[act, None] + h * np.array([-1.0, 0.0, 1.0]), 0.0, np.pi)
        v = power(pts, act)
        curv = v[:, 0] - 2 * v[:, 1] + v[:, 2]
        step = np.where(curv < 0, 0.5 * (v[:, 0] - v[:, 2]) / np.where(curv < 0, curv, -1.0), 0.0)
        bad = (curv >= 0) | (np.abs(step) > 1.0)   # not a maximum inside: move to the best stencil point
        step = np.where(bad, np.argmax(v, axis=1) - 1.0, step)
        t[act] = np.clip(t[act] + h * step, 0.0, np.pi)
        act = _unsettled(act, was_short, _short_step(h * np.abs(step), bad, tol))
        h *= 0.5
    return np.cos(t), power(t[:, None])[:, 0]


def srp_setup(mics, freqs, c, step_deg=3.0, hemisphere=None, n_grid_freqs=16):
    """Precompute the grid search for one array.

    mics : (M, 3) positions in the array frame (m). freqs : (F,) Hz of the gated spectra.
    step_deg : mean spacing of the grid. hemisphere : (3,) unit axis or None.
    n_grid_freqs : frequencies used by the grid search (spread over the band; the main lobe of a
        few-cm array is tens of degrees wide, so a coarse search cannot miss it); the refinement uses all.

    Returns a dict: grid (G, 3), steer (F', G, M) complex64, fidx (F',) indices into freqs, mics, freqs,
    c, hemisphere, step (rad), planar_normal, mirror (bool: planar array with a hemisphere, so the
    mirror image across the plane is equivalent).
    """
    mics, freqs = np.asarray(mics, float), np.asarray(freqs, float)
    hemi = None if hemisphere is None else np.asarray(hemisphere, float)
    step = np.deg2rad(step_deg)
    grid = _grids(step, None if hemi is None else tuple(hemi.tolist()))[0]
    fidx = np.unique(np.linspace(0, len(freqs) - 1, min(n_grid_freqs, len(freqs))).round().astype(int))
    steer = steering(grid, mics, freqs[fidx], c)
    kind, vec = mic_geometry(mics)
    normal = vec if kind == "planar" else None
    mirror = hemi is not None and normal is not None and abs(normal @ hemi) > 0.5
    return {"grid": grid, "steer": steer, "fidx": fidx, "mics": mics, "freqs": freqs, "c": c, "hemisphere": hemi,
            "step": step, "mirror": mirror, "planar_normal": normal,
            **_coarse_setup(grid, mics, freqs[fidx], c, step, hemi, normal)}


COARSE_FACTOR = 3     # the coarse grid's step / the fine grid's (3° → 9°: 9× fewer points)
CAP_COARSE_STEPS = 2  # fine points searched within this many coarse steps of the best coarse point


def _coarse_setup(grid, mics, freqs, c, step, hemi, normal):
    """Coarse-to-fine search of the fine grid: a grid ``COARSE_FACTOR`` times coarser, and per coarse
    point the fine points within ``CAP_COARSE_STEPS`` coarse steps of it (ascending indices, padded by
    repeating the last, so the first maximum is the exhaustive search's). The SRP's main lobe of a
    few-cm array is tens of degrees wide, so the coarse maximum lies well inside it and the cap holds the
    fine grid's maximum (the same grid point as the exhaustive search unless another lobe is within
    rounding of the main one). Planar arrays (unit ``normal`` of their plane, else None) also search the cap
    of the mirror image."""
    _, coarse, cap = _grids(step, None if hemi is None else tuple(hemi.tolist()))
    steer = steering(coarse, mics, freqs, c)
    if normal is not None:  # a planar array's mirror image has (nearly) the same power: search both caps
        mirrored = mirror(coarse, normal)
        cap = np.sort(np.c_[cap, cap[np.argmax(mirrored @ coarse.T, axis=1)]], axis=1)
    return {"coarse_steer": steer, "cap": cap}


@lru_cache(maxsize=8)
def _grids(step, hemi):
    """(grid, coarse, cap): the fine grid of ``step`` (rad) on the ``hemi`` side (a tuple, or None: the sphere),
    the coarse grid and the fine points of each coarse cap (:func:`_cap_indices`). They do not depend on
    the mics, so the arrays of a session share them (read-only): the caps' search was ~5 % of the
    frontend on an 11-array warehouse."""
    h = None if hemi is None else np.asarray(hemi, float)
    coarse_step = COARSE_FACTOR * step
    grid = fibonacci_sphere(int(np.ceil(4 * np.pi / step**2)))
    coarse = fibonacci_sphere(int(np.ceil(4 * np.pi / coarse_step**2)))
    if h is not None:
        grid = grid[grid @ h >= -0.5 * step]
        coarse = coarse[coarse @ h >= -0.5 * coarse_step]
    cap = _cap_indices(coarse, grid, np.cos(CAP_COARSE_STEPS * coarse_step))
    for a in (grid, coarse, cap):
        a.setflags(write=False)
    return grid, coarse, cap


def steering(u, mics, freqs, c):
    """Steering phasors ``exp(−j2π f u·m / c)`` for directions u (G, 3), mics (M, 3) and freqs (F,) Hz:
    (F, G, M) complex64, for the grid search only (its maximum is refined with the exact :func:`srp_power`). Phases rounded to
    float32 first (≤ 1e-6 rad for a few-cm array, far below the grid's 3°): cosine and sine in single
    precision are ~10× faster than double precision's complex exponential, which took ~12 ms of every
    process's first DOA (16 × 4584 × 6 phasors)."""
    phase = ((-2 * np.pi * np.asarray(freqs, float)[:, None, None]) * (u @ mics.T / c)[None]).astype(np.float32)
    out = np.empty(phase.shape, np.complex64)
    np.cos(phase, out=out.real)
    np.sin(phase, out=out.imag)
    return out


CAP_ROWS = 64  # coarse points per block of _cap_indices: a (64, G) block of cosines stays in cache (2.3 MB at
               # 3°; the whole (Gc, G) matrix was 19 MB of fresh memory in every process)


def _cap_indices(coarse, grid, cos_max):
    """Per coarse point (Gc, 3), the indices of the grid points (G, 3) with ``coarse · grid ≥ cos_max``
    (ascending), padded by repeating the row's last: (Gc, K) int, K the most in a row. Every coarse point
    must have one."""
    rows, cols = [], []
    for a in range(0, len(coarse), CAP_ROWS):
        r, k = np.nonzero(coarse[a : a + CAP_ROWS] @ grid.T >= cos_max)  # row-major: columns ascending
        rows.append(r + a)
        cols.append(k)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    counts = np.bincount(rows, minlength=len(coarse))
    first = np.r_[0, np.cumsum(counts)[:-1]]
    out = np.repeat(cols[first + counts - 1][:, None], int(counts.max()), axis=1)
    out[rows, np.arange(len(cols)) - first[rows]] = cols
    return out


def _grid_search(gt, setup, w, fidx):
    """Index of the fine grid's SRP maximum per event, coarse to fine: (F', M, J) complex64 spectra →
    (J,) int. Every product is single-threaded BLAS (these thin products are ~10× slower with OpenBLAS
    threads on a busy machine)."""
    j = gt.shape[-1]
    with single_thread_blas():
        p = np.zeros((setup["coarse_steer"].shape[1], j))
        for f in range(len(fidx)):  # one (Gc, M) @ (M, J) product per frequency
            y = setup["coarse_steer"][f] @ gt[f]
            p += w[fidx[f]] * (y.real**2 + y.imag**2)
        cand = setup["cap"][np.argmax(p, axis=0)]  # (J, K) fine-grid indices
        p = np.zeros(cand.shape)
        for f in range(len(fidx)):  # each event against its own K fine points
            y = np.matmul(setup["steer"][f][cand], gt[f].T[:, :, None])[..., 0]  # (J, K)
            p += w[fidx[f]] * (y.real**2 + y.imag**2)
    return cand[np.arange(j), np.argmax(p, axis=1)]


def srp_power(g, mics, freqs, c, u, weights=None):
    """Exact normalised SRP at directions u.

    g : (J, M, F) PHAT-normalised gated spectra. u : (J, K, 3). Returns (J, K).
    """
    weights = np.ones(len(freqs)) if weights is None else weights
    delays = u @ mics.T / c  # (J, K, M)
    p = np.empty(u.shape[:2])
    for a in range(0, len(g), SRP_CHUNK):  # a few events at a time: the (J, K, M, F) phasors stay in cache
        ph = phasors(freqs, -delays[a : a + SRP_CHUNK])  # (j, K, M, F)
        y = np.einsum("jkmf,jmf->jkf", ph, g[a : a + SRP_CHUNK])
        p[a : a + SRP_CHUNK] = (np.abs(y) ** 2 * weights).sum(-1)
    return _normalise(p, weights.sum(), len(mics))


SRP_CHUNK = 64  # events per block of srp_power (960 events at once wrote ~60 MB of phasors: 40 % slower)


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
        u = fold(u, h)
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def srp_doa(g, setup, weights=None, refine_to_deg=0.02):
    """DOA of each event.

    g : (J, M, F) PHAT-normalised gated spectra (F matches setup["freqs"]).

    Returns
    -------
    u : (J, 3) unit vectors (array frame, toward the source).
    power : (J,) normalised SRP at u (1 = one clean plane wave).
    """
    freqs, mics, c = setup["freqs"], setup["mics"], setup["c"]
    w = np.ones(len(freqs)) if weights is None else weights
    # grid search, all events at once, coarse to fine
    fidx = setup["fidx"]
    gt = np.transpose(g[:, :, fidx], (2, 1, 0)).astype(np.complex64)  # (F', M, J)
    u = setup["grid"][_grid_search(gt, setup, w, fidx)].copy()
    if setup["planar_normal"] is not None:
        u = _refine_planar(g, setup, w, u, refine_to_deg)
    else:
        u = _refine_sphere(g, setup, w, u, refine_to_deg)
    return u, srp_power(g, mics, freqs, c, u[:, None, :], w)[:, 0]


STENCIL = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], float)  # (9, 2): the refinement's 3x3 points
STENCIL_PINV = np.linalg.pinv(np.c_[np.ones(9), STENCIL, STENCIL[:, 0] ** 2, STENCIL[:, 1] ** 2,
                                    STENCIL[:, 0] * STENCIL[:, 1]])


def _stencil_step(val):
    """Quadratic fit of the SRP on the 3x3 stencil (J, 9): the step (J, 2) in stencil units to its maximum, or
    to the best stencil point where the fit has no maximum inside the stencil; and which rows did so (J,) bool."""
    coef = val @ STENCIL_PINV.T  # (J, 6): c0, bx, by, axx, ayy, axy
    hess = np.stack([np.stack([2 * coef[:, 3], coef[:, 5]], -1), np.stack([coef[:, 5], 2 * coef[:, 4]], -1)], -2)
    neg_def = (np.linalg.det(hess) > 0) & (hess[:, 0, 0] < 0)
    delta = np.zeros((len(val), 2))
    if neg_def.any():
        delta[neg_def] = -np.linalg.solve(hess[neg_def], coef[neg_def, 1:3][..., None])[..., 0]
    bad = ~neg_def | (np.abs(delta).max(axis=1) > 1.0)
    delta[bad] = STENCIL[np.argmax(val[bad], axis=1)]
    return delta, bad


SETTLED_STEP = 1.0   # × the refinement's tolerance: two fitted steps in a row this short end a refinement early


def _short_step(step, bad, tol):
    """(J,) bool: a stencil's step was a fit (``bad`` False: a maximum inside it) no longer than
    ``SETTLED_STEP × tol`` (``step`` (J,): its length in the refinement's units).

    Two such steps in a row end a row's shrinking-stencil refinement. A quadratic fit over a stencil of
    half-width h centred within c of the SRP's maximum lands off it by b h² (the cubic term; b depends on the
    SRP alone) plus O(c²). The first short step says the stencil before it was centred (c ≤ tol), so it sat
    at 4 b h²; the second, from there, moved ~3 b h² to this stencil's point: b h² ≤ tol / 3. (One short step
    alone says nothing about b: a first fit from half a grid step away landed 0.01° off a linear array's
    angle, the next step 0.004° long.) The SRP's main lobe is tens of degrees wide, so this comes stencils
    before the schedule reaches ``tol`` (warehouse 500: 2298 events × stencils of SRP against 4368)."""
    return ~bad & (step <= SETTLED_STEP * tol)


def _unsettled(act, was_short, short):
    """The rows of ``act`` (indices) still refined after a stencil step whose ``short`` (len(act),
    :func:`_short_step`) says which were fitted and short: all but those whose previous step was short too.
    ``was_short`` (every row's last step) is updated in place."""
    done = short & was_short[act]
    was_short[act] = short
    return act[~done]


def _refine_sphere(g, setup, w, u, refine_to_deg, start=0.5):
    """The grid's maxima u (J, 3) refined on the sphere: 3x3 stencil in the tangent plane, quadratic fit, shrink
    (from ``start`` grid steps) down to ``refine_to_deg``, a row done sooner after two fitted steps in a row
    that short (:func:`_short_step`)."""
    h, tol = start * setup["step"], np.deg2rad(refine_to_deg)  # the grid's best point: about half a step off
    u, act, was_short = u.copy(), np.arange(len(u)), np.zeros(len(u), bool)   # rows refined (_short_step)
    while h > tol and act.size:
        e1, e2 = _tangent_basis(u[act])
        pts = u[act, None, :] + h * (STENCIL[None, :, 0:1] * e1[:, None, :] + STENCIL[None, :, 1:2] * e2[:, None, :])
        pts /= np.linalg.norm(pts, axis=-1, keepdims=True)
        delta, bad = _stencil_step(srp_power(g[act], setup["mics"], setup["freqs"], setup["c"], pts, w))
        u[act] = _fold(u[act] + h * (delta[:, 0:1] * e1 + delta[:, 1:2] * e2), setup)
        act = _unsettled(act, was_short, _short_step(h * np.linalg.norm(delta, axis=1), bad, tol))
        h *= 0.7 if bad.all() else 0.5
    return u


def _refine_planar(g, setup, w, u, refine_to_deg, start=0.5):
    """The grid's maxima u (J, 3) of a planar array refined in its mic plane. Its SRP depends only on the in-plane
    part v of u (the mics' delays are v·m / c), so the peak is found in v (a well-conditioned 2-D maximum) and
    u = v + √(1 − |v|²) n on the grid point's side of the plane (in the plane if |v| > 1). On the sphere the
    elevation is nearly flat near the plane (curvature ∝ sin² elevation): the tangent-plane refinement stopped
    up to 3.4° off on noiseless plane waves 2–15° above a 6-mic circle's plane. The stencil shrinks as
    :func:`_refine_sphere`'s (in-plane units)."""
    n = setup["planar_normal"]
    side = np.where(u @ n < 0, -1.0, 1.0)
    e1, e2 = _tangent_basis(n)
    basis = np.stack([e1, e2])  # (2, 3)
    x = u @ basis.T  # (J, 2) in-plane coordinates
    h, tol = start * setup["step"], np.deg2rad(refine_to_deg)
    act, was_short = np.arange(len(x)), np.zeros(len(x), bool)   # rows refined (_short_step)
    while h > tol and act.size:  # the last quadratic step lands far finer than h (~1e-6° noiseless)
        pts = (x[act, None, :] + h * STENCIL[None]) @ basis  # (J, 9, 3): in-plane vectors, |v| may exceed 1
        delta, bad = _stencil_step(srp_power(g[act], setup["mics"], setup["freqs"], setup["c"], pts, w))
        x[act] += h * delta
        act = _unsettled(act, was_short, _short_step(h * np.linalg.norm(delta, axis=1), bad, tol))
        h *= 0.7 if bad.all() else 0.5
    r = np.linalg.norm(x, axis=1, keepdims=True)
    up = np.sqrt(np.clip(1.0 - r**2, 0.0, None)) * side[:, None]
    v = np.where(r > 1.0, x / np.maximum(r, 1e-12), x)
    return _fold(v @ basis + up * n, setup)


DOA_SUBBANDS = 3       # the band split in this many equal parts for the DOA's band scatter (band_scatter)
SUBBAND_START = 2.0    # grid steps: each sub-band's refinement starts this wide around the full band's DOA (it can
                       # travel ~2x as far: a reflection moved the lowest band's DOA of wall arrays up to ~10°)


def band_scatter(g, setup, u, weights=None, refine_to_deg=0.1):
    """Standard deviation (rad, per tangent axis) of each DOA ``u`` (J, 3) from the scatter of the DOAs of
    ``DOA_SUBBANDS`` equal parts of the band (each the SRP maximum nearest ``u`` on its frequencies alone).

    A reflection that the gate cannot separate (a pulse or less behind the direct path: a wall array 10 cm
    off its wall) adds to each mic a phase error ∝ a sin(2π f Δ), which changes across the band; the
    sub-band DOAs then disagree about as much as the full band's errs (noise alike). Sub-band k weighs in the
    full band's DOA by its information I_k = Σ_f w_f f² (the SRP's curvature: a delay's phase grows with f);
    were the sub-band DOAs u_k independent with variances ∝ 1 / I_k, the full band's (their weighted mean)
    per-axis variance is Σ_k I_k |u_k − u|² / (2 (K − 1) Σ_k I_k). For planar and 3-D arrays (linear ones
    measure one angle: srp_cone).

    g : (J, M, F) PHAT-normalised gated spectra on ``setup["freqs"]`` (:func:`srp_setup`).
    """
    freqs = setup["freqs"]
    w = np.ones(len(freqs)) if weights is None else np.asarray(weights, float)
    parts = np.array_split(np.arange(len(freqs)), DOA_SUBBANDS)
    info = np.array([np.sum(w[idx] * freqs[idx] ** 2) for idx in parts])
    refine = _refine_planar if setup["planar_normal"] is not None else _refine_sphere
    sq = np.zeros(len(u))
    for idx, i_k in zip(parts, info):
        uk = refine(g[:, :, idx], {**setup, "freqs": freqs[idx]}, w[idx], u, refine_to_deg, SUBBAND_START)
        sq += i_k * np.arccos(np.clip(np.sum(uk * u, axis=1), -1.0, 1.0)) ** 2
    return np.sqrt(sq / (2 * (len(parts) - 1) * info.sum()))
