"""The baseline: Wang et al. (T-RO 2024) initialisation, written from the paper's description.

J. Wang et al., "SLAM-based joint calibration of multiple asynchronous microphone arrays and sound source
localization", IEEE T-RO 2024. Their pipeline uses TDOA-M, DOA and odometry (no TDOA-S); its
initialisation, reproduced here step by step, is:

1. Sources: the reference array's DOAs triangulated with the odometry (``init.init_sources``: the
   least-squares start point of the odometry chain on the reference rays), then fused with the DOA
   rays as Wang et al. do: ``s_k ← (s_k + |s_k| u_ref,k) / 2``.
2. Ranges: for every array, the distance to each source from its DOAs alone. The angle between two of
   the array's DOAs and the known distance between the two (reference-frame) sources give one
   law-of-cosines equation ``b_a² + b_b² − 2 b_a b_b cos θ_ab = |s_a − s_b|²``. As in the paper, windows
   of 4 sources (6 equations, 4 unknown ranges) are solved by least squares from 2 m; each source's
   range is the outlier-filtered mean of its window estimates (windows: see :func:`range_windows`).
3. Pose: SVD (Kabsch) alignment of the range-scaled DOAs ``b u`` (array frame) with the sources.
4. Clocks: offset and drift by a straight-line fit of ``TDOA-M − (b_i − d_ref)/c`` against emission
   time, refitted once without the points whose residual z-score exceeds 2.

``estimator.calibrate(features, method="wang")`` calls :func:`wang_initialise` and then runs the joint
NLS on TDOA-M + DOA + odometry from it (Wang et al.'s graph-SLAM step; ours adds a robust first pass and
outlier removal, which change nothing on outlier-free data). Drifts are relative to the reference array
(its drift is fixed to 0 without TDOA-S).
"""
from __future__ import annotations

import itertools

import numpy as np
from calib.robust import MAD_TO_SIGMA, mad_std

from .init import ObservabilityError, init_sources, kabsch
from .problem import empty_state

WINDOW = 4                  # sources per range window (Wang et al.: 4 consecutive events)
SPAN = 7                    # windows are drawn within runs of this many consecutive events (see range_windows)
RANGE_START = 2.0           # m, Wang et al.'s starting guess for every range
RANGE_BOUNDS = (1e-2, 1e3)  # m
CLOCK_Z_REJECT = 2.0        # z-score beyond which a TDOA-M point is left out of the clock refit


def wang_sources(p, fuse=True):
    """Source positions (K, 3) in the reference frame from the reference DOAs and the odometry.

    ``fuse``: average each odometry-chain source with the point at the same range on its reference
    DOA ray (Wang et al.'s DOA/odometry fusion).
    """
    s = init_sources(p)
    if isinstance(s, list):  # hypotheses: several only for mirror-ambiguous reference DOAs (refused upstream)
        s = s[0]
    if fuse:
        m = p.doa.arr == p.ref
        j, u = p.doa.ev[m], p.doa.u[m]
        s = s.copy()
        s[j] = 0.5 * (s[j] + np.linalg.norm(s[j], axis=1, keepdims=True) * u)
    return s


def window_ranges(cosang, dist2, pairs, b0, max_iter=25):
    """Batched bounded Levenberg–Marquardt on law-of-cosines windows.

    cosang, dist2 : (W, P) cos θ_ab between the array's DOAs and |s_a − s_b|² (m²) for the P pairs.
    pairs : (P, 2) indices of the pair members inside a window of w sources.
    b0 : (W, w) starting ranges (m).
    Each window stops by its own test (a step accepted with a relative decrease <= 1e-8, or the damping
    past 1e8), as a solve of that window alone would; the batch only iterates the windows still running.
    Returns ranges (W, w) and the final cost ½Σr² (W,).
    """
    W, w = b0.shape
    a, b_ = pairs[:, 0], pairs[:, 1]
    rows = np.arange(len(pairs))

    def resid(b, ca, d2):
        ba, bb = b[:, a], b[:, b_]
        return ba * ba + bb * bb - 2.0 * ba * bb * ca - d2

    b = np.clip(b0.astype(float), *RANGE_BOUNDS)
    r = resid(b, cosang, dist2)
    cost = 0.5 * np.sum(r * r, axis=1)
    lam = np.full(W, 1e-3)
    act = np.arange(W)   # the windows still iterating
    for _ in range(max_iter):
        ca, d2, bk, rk, ck, lk = cosang[act], dist2[act], b[act], r[act], cost[act], lam[act]
        ba, bb = bk[:, a], bk[:, b_]
        J = np.zeros((len(act), len(pairs), w))
        J[:, rows, a] = 2.0 * ba - 2.0 * bb * ca
        J[:, rows, b_] = 2.0 * bb - 2.0 * ba * ca
        Jt = J.transpose(0, 2, 1)
        H = Jt @ J
        g = (Jt @ rk[..., None])[..., 0]
        dH = np.diagonal(H, axis1=1, axis2=2)
        floor = 1e-9 * dH.max(axis=1, keepdims=True) + 1e-12    # keeps A regular where a column vanishes
        A = H + (lk[:, None] * np.maximum(dH, floor) + floor)[:, :, None] * np.eye(w)[None]
        step = -np.linalg.solve(A, g[..., None])[..., 0]
        cand = np.clip(bk + step, *RANGE_BOUNDS)
        r2 = resid(cand, ca, d2)
        cost2 = 0.5 * np.sum(r2 * r2, axis=1)
        ok = cost2 < ck
        b[act] = np.where(ok[:, None], cand, bk)
        r[act] = np.where(ok[:, None], r2, rk)
        small = ok & (ck - cost2 <= 1e-8 * ck)
        cost[act] = np.where(ok, cost2, ck)
        lam[act] = lk = np.where(ok, lk / 3.0, lk * 4.0)
        act = act[~(small | (lk > 1e8))]
        if not len(act):
            break
    return b, cost


def robust_mean(v):
    """Mean of ``v`` without the values beyond 3 scaled MADs of the median (all kept if fewer than 3)."""
    v = np.asarray(v, float)
    if v.size < 3:
        return float(np.mean(v))
    med = np.median(v)
    if np.isnan(med):
        mad = mad_std(v, center=med)
    else:   # no NaN: mad_std's value without its NaN-aware median (several times slower on ~20 values)
        mad = MAD_TO_SIGMA * np.median(np.abs(v - med))
    keep = np.abs(v - med) <= 3.0 * max(mad, 1e-9)
    return float(np.mean(v[keep]))


def range_windows(n, window=WINDOW, span=SPAN):
    """Index sets (W, w) of the law-of-cosines windows over n sources in emission order.

    n >= window. Every ``window``-subset of each run of ``span`` consecutive sources (all subsets when
    n <= span). Wang et al. slide one window of 4 consecutive sources (simulations) or take all 4-subsets
    (real data). Sliding windows alone leave a trajectory's first and last sources in a single window,
    whose local minimum then decides their range (7 of 120 noise-free arrays off by metres); all subsets
    cost C(14, 4) = 1001 windows per array. Here each source sits in up to C(span − 1, 3) = 20 windows
    and the outlier-filtered mean discards the odd wrong one (0 of 120 off, 2.7 ms per array).
    """
    span = min(max(span, window), n)
    base = np.array(list(itertools.combinations(range(span), window)))
    return np.unique((np.arange(n - span + 1)[:, None, None] + base[None]).reshape(-1, window), axis=0)


def wang_ranges(us, ss, window=WINDOW, span=SPAN, start=RANGE_START):
    """Distances from each array to the sources it has DOAs for, from its DOAs and the sources.

    us : list over arrays of (n_i, 3) unit DOAs (array frame) for n_i >= ``window`` events, in emission order.
    ss : list over arrays of (n_i, 3) the same events' source positions (reference frame).
    Returns a list of ranges (n_i,) and a list of RMS law-of-cosines residuals (m²) of those ranges,
    one per array.
    All arrays' windows are solved in one batch.
    """
    pairs = np.array(list(itertools.combinations(range(window), 2)))
    cos_all, d2_all, idx_all = [], [], []
    for u, s in zip(us, ss):
        idx = range_windows(len(u), window, span)
        ia, ib = idx[:, pairs[:, 0]], idx[:, pairs[:, 1]]               # (W, P)
        cos_all.append(np.clip(np.sum(u[ia] * u[ib], axis=2), -1.0, 1.0))
        d2_all.append(np.sum((s[ia] - s[ib]) ** 2, axis=2))
        idx_all.append(idx)
    n_win = sum(len(i) for i in idx_all)
    b, _ = window_ranges(np.vstack(cos_all), np.vstack(d2_all), pairs, np.full((n_win, window), start))
    ranges, res, k0 = [], [], 0
    for idx, ca, d2 in zip(idx_all, cos_all, d2_all):
        bi = b[k0:k0 + len(idx)]
        k0 += len(idx)
        rg = np.array([robust_mean(bi[idx == e]) for e in range(int(idx.max()) + 1)])
        ranges.append(rg)
        # consistency of the combined ranges with every window equation (wrong-minimum windows excluded)
        ba, bb = rg[idx[:, pairs[:, 0]]], rg[idx[:, pairs[:, 1]]]
        res.append(float(np.sqrt(np.mean((ba * ba + bb * bb - 2.0 * ba * bb * ca - d2) ** 2))))
    return ranges, res


def pose_by_alignment(u, ranges, s):
    """Rotation (3, 3) array → reference frame and position (3,) by SVD alignment of ``ranges·u`` with ``s``."""
    q = ranges[:, None] * u
    qc, sc = q.mean(0), s.mean(0)
    R, _ = kabsch(q - qc, s - sc)
    return R, sc - R @ qc


def clock_line_fit(x, y, z_reject=CLOCK_Z_REJECT):
    """Fit ``y ≈ offset + drift·x`` by least squares, then refit without points of residual z-score > z_reject.

    x, y : (n,). Returns offset, drift, number of points left out.
    """
    if len(y) == 0:
        return 0.0, 0.0, 0
    if len(y) == 1:
        return float(y[0]), 0.0, 0
    A = np.column_stack([np.ones_like(x), x])
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    r = y - A @ coef
    sd = r.std()
    keep = np.abs(r - r.mean()) <= z_reject * sd if sd > 0 else np.ones(len(y), bool)
    if 2 <= keep.sum() < len(y):
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
    return float(coef[0]), float(coef[1]), int(len(y) - keep.sum())


def wang_initialise(p, *, fuse=True):
    """Wang et al.'s initial state for problem ``p`` (``estimator.problem``; TDOA-S rows are ignored).

    Returns (state, info): state as in ``estimator.problem`` (reference drift 0: drifts relative to the
    reference array); info holds per-array diagnostics (law-of-cosines RMS residual, rejected TDOA-M).
    """
    folded = [str(p.names[i]) for i in range(p.N) if np.any(p.fold[i])]
    if folded:
        # The ranges come from angles between an array's DOAs, which a mirror-ambiguous DOA does not give.
        raise ObservabilityError(f"array {folded[0]} has mirror-ambiguous (planar-array) DOAs: Wang et al.'s "
                                 "initialisation needs 3-D DOAs; use the hybrid method")
    st = empty_state(p)
    st.s = s = wang_sources(p, fuse=fuse)
    c, beta, t = p.c, p.beta, p.t
    d_ref = np.linalg.norm(s - st.x[p.ref], axis=1)
    arrays = [i for i in range(p.N) if i != p.ref]
    doas = []
    for i in arrays:
        md = p.doa.arr == i
        if md.sum() < WINDOW:
            raise ObservabilityError(f"array {p.names[i]} has DOAs for {int(md.sum())} event(s); Wang et al.'s "
                                     f"initialisation needs >= {WINDOW}")
        order = np.argsort(p.doa.ev[md], kind="stable")
        doas.append((p.doa.ev[md][order], p.doa.u[md][order]))
    ranges, res = wang_ranges([u for _, u in doas], [s[j] for j, _ in doas])
    rejected = {}
    for i, (j, u), b in zip(arrays, doas, ranges):
        st.R[i], st.x[i] = pose_by_alignment(u, b, s[j])
        # Clocks from the ranges where the array has a DOA for the event, else from the aligned pose.
        dist = np.linalg.norm(s - st.x[i], axis=1)
        dist[j] = b
        mm = p.tdoa_m.arr == i
        jm = p.tdoa_m.ev[mm]
        y = p.tdoa_m.val[mm] - (dist[jm] - d_ref[jm]) / c
        x_fit = t[jm] + dist[jm] / c + beta
        st.offset[i], st.drift[i], rejected[str(p.names[i])] = clock_line_fit(x_fit, y)
    range_res = {str(p.names[i]): r for i, r in zip(arrays, res)}
    return st, {"range_rms_residual_m2": range_res, "clock_points_rejected": rejected}
