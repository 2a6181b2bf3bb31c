"""Measurement factors: each one residual (whitened by its sigma) and its analytic Jacobian, in one place.

Every factor is a function ``f(p, st, lay) -> Factor`` (a :class:`~calib.estimator.problem.Problem`,
a ``State`` and a ``Layout``): ``kind`` (str), ``r`` (m,) whitened residuals, ``J`` (m, n) Jacobian
w.r.t. the free parameters of ``lay`` (a sparse :class:`Jacobian` from :func:`jacobian`, filled by
:func:`put`; a dense array works too), ``row`` (m,) the measurement's row in its CSV (for
reports), ``dim`` residuals per measurement, ``robust`` (bool) whether the robust loss applies, ``sigma``
the whitening scale (SI).

Adding a measurement kind = its spec (``calib.kinds.KindSpec``), its factor function and (rows of its own)
a rows builder, joined by :func:`register` (docs/architecture.md, "Adding a measurement kind").
Clock model (docs/architecture.md): arrival a_ij = (1+δ_i)(t_j + e_j + |s_j − x_i|/c) + τ_i + β δ_i.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from calib import kinds as K
from calib.geometry import yaw_rotate
from calib.kinds import KINDS

from .problem import arrival_sources, doa_rows, event_rows, speed, tdoa_m_rows, tdoa_s_rows, velocity_error



class Jacobian:
    """A factor's Jacobian (m, n) as a sparse accumulator: ``put`` appends (row, col, value) chunks.

    Each measurement row touches one or two arrays and one or two sources, so J is almost all zeros for
    large problems; :func:`calib.estimator.solver.linearise` stacks the chunks of all factors into one
    dense or ``scipy.sparse`` matrix. ``np.asarray(J)`` / ``J.toarray()`` give the dense (m, n) matrix.
    """

    __slots__ = ("shape", "chunks")

    def __init__(self, m, n):
        self.shape = (int(m), int(n))
        self.chunks = []  # (rows, cols, vals), each (k,); pairs distinct within a chunk

    def add(self, rows, cols, vals):
        self.chunks.append((rows, cols, vals))

    def toarray(self):
        out = np.zeros(self.shape)
        for r, c, v in self.chunks:
            out[r, c] += v  # distinct (row, col) pairs within a chunk: buffered addition is exact
        return out

    def __array__(self, dtype=None, copy=None):
        out = self.toarray()
        return out if dtype is None else out.astype(dtype)


def jacobian(m, lay):
    """An empty (m, n free parameters) Jacobian for a factor to ``put`` into."""
    return Jacobian(m, lay.n)


def put(J, rows, cols, vals):
    """J[rows, cols] += vals for the free columns (cols >= 0). rows (m,), cols (m, q), vals (m, q) or broadcast.

    ``J`` is a :class:`Jacobian` (sparse accumulator) or a dense (m, n) array. Within one call the (row, col)
    pairs are distinct (a row names each parameter once), so buffered fancy-index addition is exact.
    """
    cols = np.asarray(cols).reshape(len(rows), -1)
    shape = cols.shape
    # 32-bit indices where they fit (half the memory of a large problem's Jacobian)
    itype = np.int32 if max(int(np.max(rows, initial=0)), int(cols.max(initial=0))) < np.iinfo(np.int32).max else np.int64
    rr, cc = np.repeat(np.asarray(rows, itype), shape[1]), cols.ravel().astype(itype, copy=False)
    free = cc >= 0
    vals = np.asarray(vals, float)
    if vals.size != shape[0] * shape[1]:
        vals = np.broadcast_to(vals.reshape(shape[0], -1), shape)
    vv = vals.ravel()
    if not free.all():
        rr, cc, vv = rr[free], cc[free], vv[free]
    if not len(cc):
        return
    if isinstance(J, Jacobian):
        J.add(rr, cc, vv)
    else:
        J[rr, cc] += vv


def _dist(st, arr, ev, s=None):
    """Distances (m,) and unit vectors (m, 3) from arrays ``arr`` to sources ``ev`` (of ``s``, default ``st.s``)."""
    w = (st.s if s is None else s)[ev] - st.x[arr]
    d = np.linalg.norm(w, axis=1)
    return d, w / d[:, None]


class Shifts(NamedTuple):
    """A moving source's arrival shifts at a state (:func:`arrival_shifts`): ``sh`` (N, K) s, their
    derivatives ``ds`` (N, K, 3) with respect to the source (the array's position: −ds), ``dyaw`` (N, K)
    with respect to the odometry yaw and ``dcs`` (N, K) with respect to ln c (``State.cs``)."""
    sh: np.ndarray
    ds: np.ndarray
    dyaw: np.ndarray
    dcs: np.ndarray


def arrival_shifts(p, st):
    """The matched filter's arrival shift of every array and event at ``st`` for a source moving during the
    sweep (``p.motion``, :class:`~calib.estimator.problem.SourceMotion`): β ṙ_ij / c, or the measured curve
    at ε = ṙ_ij / c, ṙ the range rate from the displaced source; None for a stopped one. In the factor, so
    that every solve fits the shifts at its own geometry and its Jacobian holds their derivative (β|v|/(c r)
    of the range's: 0.07 on test_motion_noise's scene) instead of passes that hold them fixed."""
    m = p.motion
    if m is None:
        return None
    psi = float(st.odo_yaw[0]) if len(st.odo_yaw) else 0.0
    v, disp = yaw_rotate(m.vel, psi), yaw_rotate(m.disp, psi)
    w = (st.s + disp)[None] - st.x[:, None]
    d = np.linalg.norm(w, axis=2)
    u = w / np.maximum(d, 1e-9)[..., None]
    rdot = np.einsum("kc,nkc->nk", v, u)
    c = speed(p, st)
    if m.curve is not None:
        x, y = (np.asarray(a, float) for a in m.curve)
        sh = np.interp(rdot / c, x, y)
        seg = np.clip(np.searchsorted(x, rdot / c) - 1, 0, len(x) - 2)
        inside = (rdot / c > x[0]) & (rdot / c < x[-1])   # (np.interp holds the ends)
        g = np.where(inside, (y[seg + 1] - y[seg]) / (x[seg + 1] - x[seg]), 0.0) / c
    else:
        sh, g = m.beta * rdot / c, np.full(rdot.shape, m.beta / c)
    ds = g[..., None] * (v[None] - rdot[..., None] * u) / np.maximum(d, 1e-9)[..., None]
    turn = lambda a: np.column_stack([-a[:, 1], a[:, 0], np.zeros(len(a))])   # noqa: E731  d(Rz(ψ) a)/dψ
    dyaw = g * np.einsum("kc,nkc->nk", turn(v), u) + np.einsum("nkc,kc->nk", ds, turn(disp))
    return Shifts(sh, ds, dyaw, -g * rdot)   # (d sh / d ln c = −g ṙ: ε = ṙ/c)


@dataclass
class Factor:
    """One kind's factor evaluated at a state: whitened residuals r (m,), their Jacobian J (m, n) (a
    :class:`Jacobian`, or dense), the CSV line of each measurement ``row``, ``dim`` residuals per
    measurement, whether the robust loss applies, and the whitening sigma (SI units)."""
    kind: str
    r: np.ndarray
    J: object
    row: np.ndarray
    dim: int
    robust: bool
    sigma: float
    sigma_rows: np.ndarray | None = None   # per-residual sigma when per-array components apply

    @property
    def row_sigma(self):
        """The sigma of each residual: ``sigma_rows`` or ``sigma`` for all."""
        return self.sigma if self.sigma_rows is None else self.sigma_rows


def _out(kind, r, J, row, dim, robust, sigma):
    return Factor(kind, r, J, row, dim, robust, sigma)


def tdoa_s(p, st, lay):
    """TDOA-S: a_{i,b} − a_{i,a} = (1+δ_i)(t_b − t_a + e_b − e_a + (d_ib − d_ia)/c); each row whitened by the
    type's sigma × its row's scale (``TdoaSRows.scale``: its array's arrival sigma, problem.arrival_scales)."""
    i, a, b, z = p.tdoa_s.arr, p.tdoa_s.a, p.tdoa_s.b, p.tdoa_s.val
    m, c, sig0 = len(z), speed(p, st), p.sigma["tdoa_s"]
    J = jacobian(m, lay)
    if m == 0:
        return _out("tdoa_s", np.zeros(0), J, p.tdoa_s.row, 1, True, sig0)
    sig = sig0 * p.tdoa_s.scale
    src = arrival_sources(p, st)
    da, na = _dist(st, i, a, src)
    db, nb = _dist(st, i, b, src)
    h = p.t[b] - p.t[a] + st.e[b] - st.e[a] + (db - da) / c
    g = 1.0 + st.drift[i]
    r = (g * h - z) / sig
    gc = (g / (c * sig))[:, None]
    cols = [lay.drift[i], lay.x[i], lay.s[b], lay.s[a], lay.e[b], lay.e[a]]
    vals = [h / sig, -gc * (nb - na), gc * nb, -gc * na, g / sig, -g / sig]
    sh = arrival_shifts(p, st)
    if sh is not None:   # a moving source: shift_b − shift_a of the array's arrivals
        r = r + (sh.sh[i, b] - sh.sh[i, a]) / sig
        dsb, dsa = sh.ds[i, b] / sig[:, None], sh.ds[i, a] / sig[:, None]
        vals[1:4] = [vals[1] - dsb + dsa, vals[2] + dsb, vals[3] - dsa]
        cols, vals = cols + [np.full(m, lay.odo_yaw[0])], vals + [(sh.dyaw[i, b] - sh.dyaw[i, a]) / sig]
    if src is not st.s:   # the velocity errors move the arrivals as source shifts of β δv
        cols, vals = cols + [lay.dv[b], lay.dv[a]], vals + [p.motion.beta * gc * nb, -p.motion.beta * gc * na]
    k = _cs_col(lay)
    if k >= 0:   # d/d ln c: −(1+δ)(d_b − d_a)/c, and the moving source's shifts
        cols.append(np.full(m, k))
        vals.append(-gc[:, 0] * (db - da) + (0.0 if sh is None else (sh.dcs[i, b] - sh.dcs[i, a]) / sig))
    put(J, np.arange(m), np.column_stack(cols), np.column_stack(vals))
    return _rows_out("tdoa_s", r, J, p.tdoa_s, sig0, sig)


def tdoa_m(p, st, lay):
    """TDOA-M: a_ij − a_{ref,j}; each row whitened by the type's sigma × its row's scale (``TdoaMRows.scale``)."""
    i, j, z = p.tdoa_m.arr, p.tdoa_m.ev, p.tdoa_m.val
    ref, m, c, sig0, beta = p.ref, len(z), speed(p, st), p.sigma["tdoa_m"], p.beta
    J = jacobian(m, lay)
    if m == 0:
        return _out("tdoa_m", np.zeros(0), J, p.tdoa_m.row, 1, True, sig0)
    sig = sig0 * p.tdoa_m.scale
    src = arrival_sources(p, st)
    di, ni = _dist(st, i, j, src)
    w0 = src[j] - st.x[ref]   # (the reference array for every row: one broadcast, no gather)
    d0 = np.linalg.norm(w0, axis=1)
    n0 = w0 / d0[:, None]
    te = p.t[j] + st.e[j]
    gi, g0 = 1.0 + st.drift[i], 1.0 + st.drift[ref]
    model = (gi * (te + di / c) + st.offset[i] + beta * st.drift[i]
             - g0 * (te + d0 / c) - st.offset[ref] - beta * st.drift[ref])
    r = (model - z) / sig
    one = 1.0 / sig
    ds = (gi[:, None] * ni - g0 * n0) / (c * sig)[:, None]
    cols = [lay.drift[i], np.full(m, lay.drift[ref]), lay.offset[i], np.full(m, lay.offset[ref]), lay.x[i],
            np.tile(lay.x[ref], (m, 1)), lay.s[j], lay.e[j]]
    vals = [(te + di / c + beta) / sig, -(te + d0 / c + beta) / sig, one, -one, -(gi / (c * sig))[:, None] * ni,
            (g0 / (c * sig))[:, None] * n0, ds, (gi - g0) / sig]
    sh = arrival_shifts(p, st)
    if sh is not None:   # a moving source: shift_i − shift_ref of the event's arrivals
        r = r + (sh.sh[i, j] - sh.sh[ref, j]) / sig
        dsi, ds0 = sh.ds[i, j] / sig[:, None], sh.ds[ref, j] / sig[:, None]
        vals[4:7] = [vals[4] - dsi, vals[5] + ds0, vals[6] + dsi - ds0]
        cols, vals = cols + [np.full(m, lay.odo_yaw[0])], vals + [(sh.dyaw[i, j] - sh.dyaw[ref, j]) / sig]
    if src is not st.s:   # the velocity errors move the arrivals as source shifts of β δv
        cols, vals = cols + [lay.dv[j]], vals + [p.motion.beta * ds]
    k = _cs_col(lay)
    if k >= 0:   # d/d ln c: −((1+δ_i) d_i − (1+δ_ref) d_ref)/c, and the moving source's shifts
        cols.append(np.full(m, k))
        vals.append(-(gi * di - g0 * d0) / (c * sig) + (0.0 if sh is None else (sh.dcs[i, j] - sh.dcs[ref, j]) / sig))
    put(J, np.arange(m), np.column_stack(cols), np.column_stack(vals))
    return _rows_out("tdoa_m", r, J, p.tdoa_m, sig0, sig)


def _cs_col(lay):
    """The column of ln c (``State.cs``) in ``lay`` (-1: the speed of sound is not estimated)."""
    cs = getattr(lay, "cs", None)
    return -1 if cs is None else int(cs[0])


def _rows_out(kind, r, J, rows, sig0, sig):
    """A one-residual-per-row factor whitened per row (``sig`` (m,)); ``sigma_rows`` only where the rows' scales
    are not all 1 (so a problem without per-row scales is evaluated exactly as before)."""
    uniform = bool(np.all(rows.scale == 1.0))
    return Factor(kind, r, J, rows.row, 1, True, sig0, None if uniform else sig)


# [w]x = [[0, −w2, w1], [w2, 0, −w0], [−w1, w0, 0]] as columns of (w0, w1, w2, −w0, −w1, −w2, 0)
_SKEW = np.array([6, 5, 1, 2, 6, 3, 4, 0, 6])


def doa(p, st, lay):
    """DOA: R_iᵀ (s_j − x_i)/|s_j − x_i| − u_ij, three components per measurement; a planar array's prediction as
    the frontend steered it with the declared c when c is free or moved (:func:`_planar_steering`)."""
    i, j, u = p.doa.arr, p.doa.ev, p.doa.u
    m = len(i)
    sig = p.sigma["doa"] * np.repeat(p.doa.scale, 3)  # per residual: the type's sigma × the row's scale
    J = jacobian(3 * m, lay)
    if m == 0:
        return _out("doa", np.zeros(0), J, p.doa.row, 3, True, p.sigma["doa"])
    t_doa = _doa_time(p)
    d, n = _dist(st, i, j, _doa_sources(p, st, t_doa))
    Rt = np.ascontiguousarray(np.transpose(st.R[i], (0, 2, 1)))   # (the memory order H @ Rt would have)
    v = np.einsum("kab,kb->ka", Rt, n)
    # Mirror-ambiguous (planar) arrays: compare the prediction folded to the measured side, v → H v with
    # the reflection H = I − 2 n nᵀ where n·v < 0 (so the Jacobians are multiplied by H there too).
    foldable = bool(p.fold.any())   # no folded array: n·v = 0, nothing flips
    if foldable:
        nf = p.fold[i]
        flip = np.einsum("ka,ka->k", nf, v) < 0
    folded = foldable and bool(flip.any())   # else H = I: skip its products (the same values, fewer calls)
    if folded:
        H = np.eye(3)[None] - 2.0 * flip[:, None, None] * nf[:, :, None] * nf[:, None, :]
        Rt = H @ Rt
        v = np.einsum("kab,kb->ka", Rt, n)
    # whitened along each row's axes (``DoaRows.axes``: its fit's principal tangent axes, then u)
    B = p.doa.axes
    sig = sig * p.doa.axis_scale.ravel()
    k_cs = _cs_col(lay)
    steered = _planar_steering(p, st, i, v) if k_cs >= 0 or _kappa(st) != 0.0 else None
    r = np.einsum("kab,kb->ka", B, (v if steered is None else steered.q) - u).ravel() / sig
    # dv/dφ = H [w]x with w = Rᵀn (unfolded) for R → R Exp(φ); dv/ds = H Rᵀ (I − n nᵀ)/d = −dv/dx
    w = np.einsum("kab,kb->ka", H, v) if folded else v  # H is its own inverse
    # [w]x gathered from (w, −w, 0) in one indexing (exact negations, +0.0 on the diagonal)
    wx = np.concatenate([w, -w, np.zeros((m, 1))], axis=1)[:, _SKEW].reshape(m, 3, 3)
    vx = H @ wx if folded else wx
    P = (np.eye(3)[None] - n[:, :, None] * n[:, None, :]) / d[:, None, None]
    dvds = Rt @ P
    Bq = B if steered is None else B @ steered.dv   # the steered prediction's chain rule (planar rows)
    vals = (Bq @ np.concatenate([vx, dvds, -dvds], axis=2)).reshape(3 * m, 9) / sig[:, None]
    cols = np.column_stack([lay.rot[i], lay.s[j], lay.x[i]])
    if t_doa:   # the turned DOAs see the velocity error as a source shift of t_doa δv
        vals = np.column_stack([vals, t_doa * vals[:, 3:6]])
        cols = np.column_stack([cols, lay.dv[j]])
    if k_cs >= 0:
        vals = np.column_stack([vals, np.einsum("kab,kb->ka", B, steered.dk).ravel() / sig])
        cols = np.column_stack([cols, np.full(m, k_cs)])
    put(J, np.arange(3 * m), np.repeat(cols, 3, axis=0), vals)
    return Factor("doa", r, J, np.repeat(p.doa.row, 3), 3, True, p.sigma["doa"], sig)


def _kappa(st):
    """ln(c / c_declared) at ``st`` (``State.cs``; 0 without it)."""
    cs = vars(st).get("cs")
    return 0.0 if cs is None or not len(cs) else float(cs[0])


# |u·n| below which a planar row's elevation derivative is taken at this floor (it is 1/|u·n|: infinite in the
# plane, where the row's elevation axis is whitened by a sigma growing alike, problem.doa_axes)
PLANE_DERIVATIVE_FLOOR = 1e-3


class Steered(NamedTuple):
    """DOA predictions as the frontend steered them (:func:`_planar_steering`): q (m, 3), dq/dv (m, 3, 3)
    and dq/d ln c (m, 3)."""
    q: np.ndarray
    dv: np.ndarray
    dk: np.ndarray


def _planar_steering(p, st, i, v):
    """The DOAs v (m, 3) (array frame, unit) of arrays ``i`` as the frontend measured them: it steered with the
    declared c, so a planar array's in-plane part x = e^{−κ} v_p (κ = ln c/c_declared) completed to
    q = x + sgn(v·n) √(1 − |x|²) n (x/|x| past |x| = 1: frontend.doa._refine_planar; calib.geometry.steered_doas).
    dq/dv = e^{−κ} (I − n nᵀ) − sgn (e^{−2κ}/h) n v_pᵀ and dq/dκ = −x + sgn (|x|²/h) n, h = √(1 − |x|²). Other
    arrays (zero ``p.plane``; 3-D boards: unchanged to first order): q = v, dq/dv = I, dq/dκ = 0."""
    m = len(i)
    q, dv, dk = v.copy(), np.repeat(np.eye(3)[None], m, axis=0), np.zeros((m, 3))
    nrm = np.zeros((m, 3)) if p.plane is None else p.plane[i]
    rows = np.flatnonzero(np.any(nrm != 0, axis=1))
    if not rows.size:
        return Steered(q, dv, dk)
    s, n, w = float(np.exp(-_kappa(st))), nrm[rows], v[rows]
    a = np.einsum("ka,ka->k", w, n)
    sgn = np.where(a < 0, -1.0, 1.0)
    vp = w - a[:, None] * n
    x = s * vp
    r2 = np.einsum("ka,ka->k", x, x)
    h = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    hd = np.maximum(h, PLANE_DERIVATIVE_FLOOR)
    Pn = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    inside = r2 <= 1.0
    rn = np.sqrt(np.maximum(r2, 1e-24))
    q_in = x + (sgn * h)[:, None] * n
    q_out = x / rn[:, None]
    q[rows] = np.where(inside[:, None], q_in, q_out)
    d_in = s * Pn - ((sgn * s * s / hd)[:, None, None] * n[:, :, None] * vp[:, None, :])
    d_out = (np.eye(3)[None] - q_out[:, :, None] * q_out[:, None, :]) @ Pn * (s / rn)[:, None, None]
    dv[rows] = np.where(inside[:, None, None], d_in, d_out)
    dk[rows] = np.where(inside[:, None], -x + (sgn * r2 / hd)[:, None] * n, 0.0)
    return Steered(q, dv, dk)


def _doa_time(p):
    """t_doa (s) of a problem whose velocity error is modelled (``p.motion``; the DOAs were turned from
    ``t_doa`` after the sweep start, estimator/motion.py), else 0."""
    return float(p.motion.t_doa) if p.motion is not None and p.motion.sigma > 0 else 0.0


def _doa_sources(p, st, t_doa):
    """(K, 3) the source the turned DOAs see: ``st.s``, with a modelled velocity error ``st.s + t_doa δv``."""
    return st.s + t_doa * velocity_error(p, st) if t_doa else st.s


def emission(p, st, lay):
    """Prior on the per-interval emission-time corrections: (e_{j+1} − e_j) ~ N(0, sigma_emit²)."""
    K, sig = p.K, p.sigma["emission"]
    if sig <= 0 or K < 2 or not (lay.e >= 0).any():
        return _out("emission", np.zeros(0), jacobian(0, lay), np.zeros(0, int), 1, False, max(sig, 1.0))
    r = np.diff(st.e) / sig
    J = jacobian(K - 1, lay)
    k = np.arange(K - 1)
    put(J, k, lay.e[1:], np.full(K - 1, 1.0 / sig))
    put(J, k, lay.e[:-1], np.full(K - 1, -1.0 / sig))
    return _out("emission", r, J, np.arange(1, K), 1, False, sig)


def odometry_frame(p, st, lay):
    """Odometry in its own frame: (s_{j+1} − s_j) − Rz(ψ)(o_{j+1} − o_j), three components per step.

    ψ (``st.odo_yaw``, rad) is the odometry frame's rotation about the reference frame's z axis
    (taken as the vertical: the odometry's z is the reference array's z). ψ = 0 (or no ``odo_yaw`` in the
    state/layout): the plain differences (s_{j+1} − s_j) − (o_{j+1} − o_j).
    """
    K, sig = p.K, p.sigma["odometry"]
    J = jacobian(3 * max(K - 1, 0), lay)
    if K < 2:
        return _out("odometry", np.zeros(0), J, np.zeros(0, int), 3, False, sig)
    psi = float(st.odo_yaw[0])
    yaw_col = int(lay.odo_yaw[0])
    do, k = np.diff(p.odom, axis=0), np.arange(3 * (K - 1))
    if psi != 0.0:
        do = yaw_rotate(do, psi)
    r = ((st.s[1:] - st.s[:-1] - do) / sig).ravel()   # (np.diff's subtraction, without its wrapper)
    put(J, k, lay.s[1:].ravel(), np.full(3 * (K - 1), 1.0 / sig))
    put(J, k, lay.s[:-1].ravel(), np.full(3 * (K - 1), -1.0 / sig))
    if yaw_col >= 0:
        # d(Rz(ψ) Δo)/dψ = (−y', x', 0) of the rotated step (x', y', z') = Rz(ψ) Δo
        drot = np.column_stack([-do[:, 1], do[:, 0], np.zeros(K - 1)])
        put(J, k, np.full(3 * (K - 1), yaw_col), -drot.ravel() / sig)
    return _out("odometry", r, J, np.repeat(np.arange(1, K), 3), 3, False, sig)


def cone(p, st, lay):
    """Cone (linear arrays, 2-mic pairs): e^{−κ} aᵀ R_iᵀ (s_j − x_i)/|s_j − x_i| − cos θ_ij, one per measurement
    (κ = ln c/c_declared: the frontend steered with the declared c; the scale only when c is free or moved).

    ``a`` (array frame) is the array's axis, θ the measured angle between it and the source direction
    (``p.cone``; ``problem.build_problem`` reads them from meta ``doa_axes``). The roll about the
    axis does not enter (its rotation component is fixed in the layout). Whitened by ``sigma_cone``
    (rad): the cosine error is sin θ · δθ ≤ δθ.
    """
    i, j, c0 = p.cone.arr, p.cone.ev, p.cone.cos
    m, sig = len(i), p.sigma["cone"]
    J = jacobian(m, lay)
    if m == 0:
        return _out("cone", np.zeros(0), J, np.zeros(0, int), 1, True, sig)
    t_doa = _doa_time(p)
    d, n = _dist(st, i, j, _doa_sources(p, st, t_doa))
    a = p.cone_axis[i]                                    # (m, 3) array frame
    w = np.einsum("kba,kb->ka", st.R[i], n)               # Rᵀ n
    cos_true = np.einsum("ka,ka->k", a, w)
    cos = cos_true
    k_cs = _cs_col(lay)
    steer = k_cs >= 0 or _kappa(st) != 0.0
    if steer:   # steered with the declared c, the frontend measured e^{−κ} cos θ (clipped to ±1, frontend.doa.srp_cone)
        scale = float(np.exp(-_kappa(st)))
        gain = np.where(np.abs(scale * cos_true) <= 1.0, scale, 0.0)
        cos = np.clip(scale * cos_true, -1.0, 1.0)
    r = (cos - c0) / sig
    # R → R Exp(φ): w → w + w × φ, so d(aᵀw)/dφ = (a × w)ᵀ; d(aᵀw)/ds = (R a)ᵀ (I − n nᵀ)/d = −d/dx
    dphi = np.cross(a, w)
    b = np.einsum("kab,kb->ka", st.R[i], a)
    ds = (b - np.einsum("ka,ka->k", b, n)[:, None] * n) / d[:, None]
    cols, vals = [lay.rot[i], lay.s[j], lay.x[i]], [dphi, ds, -ds]
    if t_doa:
        cols, vals = cols + [lay.dv[j]], vals + [t_doa * ds]
    if steer:
        vals = [gain[:, None] * np.asarray(vv).reshape(m, -1) for vv in vals]
    if k_cs >= 0:   # d(e^{−κ} cos θ)/dκ = −e^{−κ} cos θ
        cols, vals = cols + [np.full(m, k_cs)], vals + [-gain * cos_true]
    put(J, np.arange(m), np.column_stack(cols), np.column_stack(vals) / sig)
    return _out("cone", r, J, p.cone.row, 1, True, sig)


def velocity(p, st, lay):
    """Prior on a moving source's velocity errors (``p.motion``, estimator/motion.py): δv_j ~ N(0, σ_v² I)
    per event, σ_v = ``p.sigma["velocity"]``; three components per event. Empty when not modelled."""
    dv, sig = velocity_error(p, st), p.sigma.get("velocity", 0.0)
    if dv is None or sig <= 0 or not (lay.dv >= 0).any():
        return _out("velocity", np.zeros(0), jacobian(0, lay), np.zeros(0, int), 3, False, max(sig, 1.0))
    K = p.K
    J = jacobian(3 * K, lay)
    put(J, np.arange(3 * K), lay.dv.ravel(), np.full(3 * K, 1.0 / sig))
    return _out("velocity", (dv / sig).ravel(), J, np.repeat(np.arange(K), 3), 3, False, sig)


def speed_prior(p, st, lay):
    """Prior on the speed of sound: ln(c / c_declared) ~ N(0, σ²), σ = ``p.sigma["speed"]`` (relative; the
    declared value's uncertainty, estimator/soundspeed.py). Empty when c is not estimated."""
    sig, k = p.sigma.get("speed", 0.0), _cs_col(lay)
    if sig <= 0 or k < 0:
        return _out("speed", np.zeros(0), jacobian(0, lay), np.zeros(0, int), 1, False, max(sig, 1.0))
    J = jacobian(1, lay)
    put(J, np.zeros(1, int), np.full(1, k), np.full(1, 1.0 / sig))
    return _out("speed", np.asarray(st.cs[:1], float) / sig, J, np.zeros(1, int), 1, False, sig)


# The estimator's half of each measurement kind (its spec, ``calib.kinds.KINDS``, says the rest): the factor
# function, and the rows builder ``build(df, index) -> Rows`` (``problem.RowIndex``) of the kinds with rows of
# their own in a features table (``spec.source``); the others' rows are derived in ``problem.build_problem``.
FACTORS = {"tdoa_s": tdoa_s, "tdoa_m": tdoa_m, "doa": doa, "odometry": odometry_frame, "emission": emission,
           "cone": cone, "velocity": velocity, "speed": speed_prior}
ROWS = {"tdoa_s": tdoa_s_rows, "tdoa_m": tdoa_m_rows, "doa": doa_rows}


def register(spec: K.KindSpec, factor: Callable[..., Factor], rows: Callable | None = None) -> K.KindSpec:
    """Add a measurement kind: its spec (``calib.kinds.KindSpec``) and its factor function. A kind with a
    table of its own gets its rows from ``rows(df, problem.RowIndex) -> problem.Rows``, by default
    :func:`~calib.estimator.problem.event_rows` (a table of event, array and value columns). Everything
    else (reading, validation, robust statistics, report, stage key) loops over the registry. Returns the spec."""
    K.register(spec)
    FACTORS[spec.name] = factor
    if spec.table is not None:
        ROWS[spec.name] = rows or event_rows(spec)
    return spec


def unregister(name: str) -> None:
    """Remove a kind added by :func:`register`."""
    K.unregister(name)
    FACTORS.pop(name, None)
    ROWS.pop(name, None)


def active_kinds(p, stage="joint"):
    """The kinds a ``stage`` of the estimator uses on problem ``p``, in registry order: those whose spec
    lists the stage; a kind whose sigma is an option (no meta key: the emission prior) only when it is > 0."""
    return [k for k in FACTORS if stage in KINDS[k].stages and (KINDS[k].noise_key or p.sigma.get(k, 0.0) > 0)]


def per_array(p, f):
    """A factor with per-array variance components applied: residual rows of array i divided by
    ``p.array_scale[kind][i]`` (its sigma relative to the type's), Jacobian rows alike; the per-residual
    sigma goes to ``sigma_rows``. Unchanged when the problem has no component for the factor's kind."""
    scale = (p.array_scale or {}).get(f.kind)
    if scale is None or len(f.r) == 0:
        return f
    s = np.repeat(np.asarray(scale, float)[p.rows(f.kind).arr], f.dim)
    J = f.J
    if isinstance(J, Jacobian):
        out = Jacobian(*J.shape)
        out.chunks = [(rr, cc, vv / s[rr]) for rr, cc, vv in J.chunks]
    else:
        out = np.asarray(J) / s[:, None]
    return dataclasses.replace(f, r=f.r / s, J=out, sigma_rows=f.row_sigma * s)


def row_arrays(p, fs):
    """The array of each stacked residual row of the factors ``fs`` (-1: rows of no array, e.g. odometry)."""
    out = []
    for f in fs:
        arr = getattr(getattr(p, f.kind, None), "arr", None)
        rows = np.repeat(arr, f.dim) if arr is not None and len(arr) * f.dim == len(f.r) else None
        out.append(rows if rows is not None else np.full(len(f.r), -1))
    return np.concatenate(out) if out else np.zeros(0, int)


def natural(f):
    """A factor's residuals in SI units (whitened residual × its row's sigma)."""
    return f.r * f.row_sigma


def evaluate(p, st, lay, kinds=None):
    """Evaluate the listed factors (default all) → list of :class:`Factor` (per-array components applied)."""
    fs = [FACTORS[k](p, st, lay) for k in (kinds or FACTORS)]
    return [per_array(p, f) for f in fs] if p.array_scale else fs
