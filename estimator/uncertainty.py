"""Uncertainty: covariance (JᵀWJ)⁻¹ with the gauge fixed by the reference array, and the CRLB.

The same machinery serves both: at the estimate it gives the ``*_std`` columns, at ground truth the
Cramér–Rao lower bound for unbiased estimators under the stated Gaussian noise.
"""
from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pandas as pd
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation

from calib.geometry import plane_normal
from calib.kinds import KINDS
from calib.tables import ARRAY_PARAMS, array_param, columns

from .factors import active_kinds
from .problem import Problem, State, build_problem, empty_state, make_layout, retract
from .solver import Schur, linearise


# Events per batch of right-hand sides when the event block's inverse is read off by solves (memory
# bound: n_events x 3 x this many doubles).
_SELECTED_INVERSE_BATCH = 256


def covariance(J, lay_n, lay=None, arrays_only=False):
    """(JᵀJ)⁻¹ for whitened residuals (Jacobi-scaled for conditioning).

    A dense J gives the dense (n, n) matrix (pseudo-inverse). A sparse J (large problems, with ``lay``)
    gives a :class:`BlockCovariance`: no n × n inverse is formed (``arrays_only``: its array block alone).
    """
    if scipy.sparse.issparse(J):
        if lay is None:
            J = J.toarray()
        else:
            return BlockCovariance(J, lay, arrays_only)
    d = np.linalg.norm(J, axis=0)
    d = np.where(d > 0, d, 1.0)
    Js = J / d
    return np.linalg.pinv(Js.T @ Js) / d[:, None] / d[None, :]


class BlockCovariance:
    """(JᵀJ)⁻¹ of a large problem as the blocks anyone reads: the full diagonal, the dense block of the
    array parameters (the inverse of the Schur complement S) and each source's 3 × 3 marginal.

    With X = H_EE⁻¹ H_EA (scaled), the event block of the inverse is H_EE⁻¹ + X S⁻¹ Xᵀ; only its diagonal
    and its 3 × 3 source blocks are formed (H_EE⁻¹'s by batched sparse solves).
    Attributes: ``diag`` (n,), ``arr_cols`` (nA,), ``arr`` (nA, nA), ``src_blocks`` (K, 3, 3) (NaN for
    fixed sources), ``shape``. ``arrays_only``: the event blocks are not formed (NaN in ``diag`` and
    ``src_blocks``): the array block costs one Schur complement, the event blocks a solve per source.
    """

    def __init__(self, J, lay, arrays_only=False):
        J = scipy.sparse.csr_matrix(J)
        n = lay.n
        self.shape, self.J, self.lay = (n, n), J, lay
        H = (J.T @ J).tocsr()
        dead = H.diagonal() <= 0
        if dead.any():  # untouched parameters: decouple them (unit diagonal), report NaN variance
            H = H + scipy.sparse.diags(dead.astype(float))
        self.system = sch = Schur(H, lay).factor(0.0)
        d, nA = sch.d, sch.nA
        Sinv = np.linalg.pinv(sch.S)
        XS = sch.X @ Sinv
        diag_s = np.empty(n)
        diag_s[:nA] = np.diag(Sinv)
        Einv = None if arrays_only else self._event_inverse_blocks(sch, lay)
        diag_s[nA:] = np.nan if arrays_only else Einv["diag"] + np.einsum("ia,ia->i", XS, sch.X)
        diag = np.empty(n)
        diag[sch.perm] = diag_s / d[sch.perm] ** 2
        diag[dead] = np.nan
        self.diag = diag
        self.arr_cols = sch.perm[:nA]
        self.arr = Sinv / d[self.arr_cols][:, None] / d[self.arr_cols][None, :]
        self.src_blocks = np.full((len(lay.s), 3, 3), np.nan) if arrays_only else \
            self._source_blocks(sch, lay, Einv, XS, dead)

    @staticmethod
    def _event_inverse_blocks(sch, lay):
        """Diagonal of H_EE⁻¹ (scaled, event order) and each source's 3 × 3 block of it."""
        nE, nA = sch.Hee.shape[0], sch.nA
        pos = np.full(lay.n, -1)
        pos[sch.perm[nA:]] = np.arange(nE)
        src = np.where(lay.s >= 0, pos[np.maximum(lay.s, 0)], -1)  # (K, 3) positions in E
        diag, blocks = np.zeros(nE), np.full((len(src), 3, 3), np.nan)
        covered = np.zeros(nE, bool)
        has = np.flatnonzero((src >= 0).all(axis=1))
        e = src[has]
        band = sch.event_inverse(e[:, :, None], e[:, None, :])   # a banded event block: its inverse's band
        if band is not None:
            blocks[has] = band
            return {"diag": sch.event_inverse(np.arange(nE), np.arange(nE)), "src": src, "blocks": blocks}
        for b in range(0, len(has), _SELECTED_INVERSE_BATCH):
            ks = has[b:b + _SELECTED_INVERSE_BATCH]
            cols = src[ks].ravel()
            rhs = np.zeros((nE, len(cols)))
            rhs[cols, np.arange(len(cols))] = 1.0
            Z = sch.lu.solve(rhs)  # (nE, 3 m)
            Zb = Z[src[ks][:, :, None], np.arange(len(cols)).reshape(-1, 3)[:, None, :]]  # (m, 3, 3)
            blocks[ks] = 0.5 * (Zb + np.transpose(Zb, (0, 2, 1)))
            diag[cols] = Z[cols, np.arange(len(cols))]
            covered[cols] = True
        rest = np.flatnonzero(~covered)  # e.g. emission corrections: one column at a time, batched
        for b in range(0, len(rest), 3 * _SELECTED_INVERSE_BATCH):
            cols = rest[b:b + 3 * _SELECTED_INVERSE_BATCH]
            rhs = np.zeros((nE, len(cols)))
            rhs[cols, np.arange(len(cols))] = 1.0
            diag[cols] = sch.lu.solve(rhs)[cols, np.arange(len(cols))]
        return {"diag": diag, "src": src, "blocks": blocks}

    @staticmethod
    def _source_blocks(sch, lay, Einv, XS, dead):
        """3 × 3 covariance of every source (unscaled; NaN where not all three coordinates are free)."""
        src = Einv["src"]
        out = np.full((len(src), 3, 3), np.nan)
        has = np.flatnonzero((src >= 0).all(axis=1))
        if not len(has):
            return out
        e = src[has]
        blk = Einv["blocks"][has] + np.einsum("kia,kja->kij", XS[e], sch.X[e])
        dd = sch.d[lay.s[has]]
        blk = blk / dd[:, :, None] / dd[:, None, :]
        blk[dead[lay.s[has]].any(axis=1)] = np.nan
        out[has] = blk
        return out

    def diagonal(self):
        return self.diag

    def with_arrays(self, other):
        """A copy whose array block (and its diagonal) is ``other``'s (a :class:`BlockCovariance` of the same
        layout, e.g. ``arrays_only``); the source blocks stay this one's."""
        out = copy.copy(self)
        out.arr, out.diag = other.arr, self.diag.copy()
        out.diag[self.arr_cols] = other.diag[other.arr_cols]
        return out

    def block(self, ix):
        """Covariance block of the parameter columns ``ix`` (array parameters, or one source's 3 columns)."""
        ix = np.asarray(ix)
        where = {int(c): k for k, c in enumerate(self.arr_cols)}
        if all(int(c) in where for c in ix):
            k = np.array([where[int(c)] for c in ix])
            return self.arr[np.ix_(k, k)]
        hit = np.flatnonzero((self.lay.s == ix[None, :]).all(axis=1)) if len(ix) == 3 else []
        if len(hit):
            return self.src_blocks[hit[0]]
        raise ValueError("only array-parameter blocks and single-source 3x3 blocks are kept for large problems")

    def sample(self, rng):
        """One draw (n,) from N(0, (JᵀJ)⁻¹): H⁻¹ Jᵀ z with z ~ N(0, I) has exactly that covariance."""
        z = rng.standard_normal(self.J.shape[0])
        return self.system.solve(self.J.T @ z)


def row_factors(p, lin, factors):
    """(M,): each residual row of ``lin`` with its (type, array)'s σ² factor (``factors``: {kind: (N,)},
    :func:`calib.estimator.variance.covariance_factors`; 1 for kinds without one)."""
    out, start = np.ones(len(lin.r)), 0
    for f in lin.factors:
        n = len(f.r)
        if f.kind in factors and n:
            out[start:start + n] = np.repeat(factors[f.kind][p.rows(f.kind).arr], f.dim)
        start += n
    return out


def inflated_rows(p, lin, factors):
    """The whitened Jacobian of ``lin``'s kept rows with each (type, array)'s rows divided by the root of
    its σ² factor (:func:`row_factors`): the Jacobian whose (JᵀJ)⁻¹ is the covariance with those arrays'
    sigmas raised."""
    return whiten(lin.J, 1.0 / row_factors(p, lin, factors))[lin.w > 0]


ARRIVAL_KINDS = ("tdoa_m", "tdoa_s")   # rows that are differences of two arrivals (docs/architecture.md)
FOLD_SIGMAS = 2.0   # a planar array's DOA this few elevation sigmas from its mic plane may be on either side


def arrival_rows(p, lin, factors):
    """The whitened TDOA rows as combinations of arrival errors: a sparse (M, N·K) matrix D with
    whitened residual error = D n, n the arrivals' errors in units of their own sigma.

    A TDOA-M row a_ij − a_ref,j and a TDOA-S row a_ib − a_ia share arrivals: every TDOA-M row of an event
    holds the reference's arrival (correlation ½ between them), consecutive TDOA-S rows share the middle
    one (−½), a TDOA-M and a TDOA-S row of the same array and event share its arrival. An arrival's sigma is
    its array's row sigma / √2 (the frontend's sigma_tdoa is √2 × its arrivals' spread) × its own arrival
    scale (``p.arrival_scale``: meta ``sigma_arrival_per_array``, problem.arrival_scales), raised by the
    largest of the array's σ² factors of the TDOA kinds (``factors``). Rows not kept (weight 0) and the
    other kinds have no entry."""
    keep = lin.w > 0
    K = p.K
    g = np.ones(p.N)
    for kind in ARRIVAL_KINDS:
        a = (p.array_scale or {}).get(kind)
        g = np.maximum(g, np.ones(p.N) if a is None else np.asarray(a, float))
    if p.arrival_scale is not None:
        g = g * np.asarray(p.arrival_scale, float)
    g = p.sigma["tdoa_s"] / np.sqrt(2.0) * g * np.sqrt(np.maximum.reduce(
        [factors.get(k, np.ones(p.N)) for k in ARRIVAL_KINDS]))
    rr, cc, vv, start = [], [], [], 0
    for f in lin.factors:
        n = len(f.r)
        if f.kind in ARRIVAL_KINDS and n:
            rows = p.rows(f.kind)
            if f.kind == "tdoa_m":
                first, second = (rows.arr, rows.ev), (np.full(n, p.ref), rows.ev)
            else:
                first, second = (rows.arr, rows.b), (rows.arr, rows.a)
            sig = np.broadcast_to(f.row_sigma, n)
            idx = start + np.arange(n)
            for (arr, ev), sign in ((first, 1.0), (second, -1.0)):
                rr.append(idx), cc.append(arr * K + ev), vv.append(sign * g[arr] / sig)
        start += n
    if not rr:
        return None
    r, c, v = np.concatenate(rr), np.concatenate(cc), np.concatenate(vv)
    k = keep[r]
    return scipy.sparse.csr_matrix((v[k], (r[k], c[k])), shape=(len(lin.r), p.N * K))


def plane_normals(meta, names):
    """(N, 3): the mic-plane normal (array frame) of each planar array in meta.json ``mics``, zeros elsewhere
    (and for every array when meta has no mics)."""
    mics = meta.get("mics") or {}
    out = np.zeros((len(names), 3))
    for i, n in enumerate(names):
        v = plane_normal(mics[str(n)]) if str(n) in mics else None
        if v is not None:
            out[i] = v
    return out


def _kind_blocks(lin, kind):
    """(factor, first row, rows) of each non-empty factor of ``kind`` in the linearisation ``lin``, in row order."""
    start = 0
    for f in lin.factors:
        n = len(f.r)
        if f.kind == kind and n:
            yield f, start, n
        start += n


def _doa_block(lin, f, start, n):
    """(s3 (m, 3) each DOA row's axis sigmas, Jw (m, 3, n) its whitened Jacobian, dense) of ``lin``'s DOA block
    (rows ``start``…``start + n`` of factor ``f``): what :func:`_array_frame_rows` and
    :func:`_array_frame_prediction` read (``block``: computed once for both)."""
    s3 = np.broadcast_to(f.row_sigma, n).reshape(-1, 3)
    Jw = lin.J[start:start + n]
    return s3, (Jw.toarray() if scipy.sparse.issparse(Jw) else np.asarray(Jw)).reshape(n // 3, 3, -1)


def _array_frame_rows(p, lin, f, start, n, block=None):
    """The DOA block of ``lin`` (rows ``start``…``start + n`` of factor ``f``) back in the array frame, in units of
    each row's sigma ``sig`` (m,) (its best axis', ``DoaRows.axis_scale`` 1): residuals r (m, 3) = (v − u) / sig and
    J (m, 3, n) the estimator's sensitivity to them, sig × Bᵀ W J_w (W = diag(1 / σ_axis) B the row's whitening,
    J_w the whitened Jacobian), so that an error ε (rad, array frame) moves the estimate by H⁻¹ Jᵀ ε / sig. The
    factor whitens along each row's own axes B (:func:`calib.estimator.problem.doa_axes`), which are arbitrary in a
    tangent plane where the fit's two stds are (nearly) equal; these are not (identity / ones axes: the block as is)."""
    B = p.doa.axes
    s3, Jw = _doa_block(lin, f, start, n) if block is None else block
    sig = s3[:, 0]
    r = np.einsum("kba,kb->ka", B, lin.r[start:start + n].reshape(-1, 3) * s3) / sig[:, None]
    J = np.einsum("kba,kbn->kan", B, Jw / s3[:, :, None]) * sig[:, None, None]
    return r, J, sig


def _array_frame_prediction(p, lin, f, start, n, block=None):
    """(m, 3, n): how the parameters move each DOA row of ``lin``'s block (``_array_frame_rows``' rows) in the
    array frame, in units of the row's sigma: Bᵀ diag(σ_axis) J_w / sig (J_w the whitened Jacobian). For a row
    whitened isotropically it equals the sensitivity ``_array_frame_rows`` gives."""
    B = p.doa.axes
    s3, Jw = _doa_block(lin, f, start, n) if block is None else block
    return np.einsum("kba,kbn->kan", B, Jw * s3[:, :, None]) / s3[:, :1, None]


# A row component the fit takes more than this share of (leverage h) tells little of its error: 1 − h stops here
MIN_RESIDUAL_SHARE = 0.1


def _leverages_along(pred, sens, cov, even):
    """(m,): the leverage of one component of each row, pred_kᵀ cov sens_k (``pred`` (m, n) how the parameters move
    it, ``sens`` (m, n) how its error moves them, ``cov`` the kept rows' (JᵀJ)⁻¹); ``even`` for every row without a
    dense ``cov``. At most 1 − MIN_RESIDUAL_SHARE."""
    h = np.full(len(pred), even) if not isinstance(cov, np.ndarray) else np.einsum("kn,nm,km->k", pred, cov, sens)
    return np.clip(h, 0.0, 1.0 - MIN_RESIDUAL_SHARE)


def planar_doa_rows(p, lin, normals, factors, cov=None):
    """The DOA rows of planar arrays with their errors as a planar array makes them: {"rows": (M,) bool, the
    DOA residuals it models; "G": (m, n) rows whose GᵀG is their part of Jᵀ C J}; None when there is none.

    A planar array measures the in-plane part of a direction, ρ = cos(el) (the mics' delays do not depend
    on the rest): an in-plane error σ_p moves the azimuth by σ_p (along the sphere) and the elevation by
    σ_p / sin(el) — near the mic plane the elevation is many times less certain than the azimuth (issue 27:
    sources within a few degrees of the plane, azimuth errors ≤ 0.3°, elevation errors 1–11°), which an
    isotropic sigma per row misses both ways. Each row's in-plane errors are its own residuals (along azimuth,
    and along elevation × sin(el)), each over the share 1 − h of its error the fit leaves in it (h its leverage
    at ``cov``, the kept rows' (JᵀJ)⁻¹; without ``cov`` the rotation's 3 of the array's 2n components, spread
    evenly): the Eicker–White (HC2) sandwich, unbiased when the rows err alike and right when they do not. An
    array's rows do not: a few reflections' rows err by 10–25° where the others err by 1° (lshape 500's A4), and
    the fit follows them little. Their mean square σ_p² taken as every row's error (before h54o) let the precise
    rows claim the reflections' error through their own (large) influence: that A4's std 6° at a 0.6° error;
    planar orientation error / std RMS 0.45 over 131 dev arrays (lshape 0.41, ushape 0.37), position 0.70; on
    simulated rows of unequal sigma 0.15–0.21 (``test_planar_rows_of_unequal_sigma_each_claim_their_own_error``;
    now 1.0–1.1). σ_p, the array's pooled in-plane
    scatter (over 2n − 3: the rotation absorbs 3), sets only where 1 / sin(el) stops: at
    √(2 / σ_p) (at el → 0, el ≈ √(2 (1 − ρ)): an error σ_p in ρ moves it by √(2 σ_p)). The lag-1 correlation
    inflation of ``factors`` (``factors["doa_correlation"]``) applies; the elevation's variance stays at least
    the row's sigma² × its array's σ² factor (``factors["doa"]``: a frontend's figure is only ever raised, as
    the sigmas themselves are), the azimuth's may go below it (on the lab preset azimuth errors were 0.1°
    against a row sigma of 0.6°: the row sigma there made the std 1.5× the errors). A row closer to the plane
    than FOLD_SIGMAS of its elevation std may be the mirror image of the truth (a stated hemisphere puts a
    source 4.7° below the plane 5° above it: moving seed 23): its elevation variance gains el². Near the
    plane the elevation is also biased, and the same way for every such row: it is read from the in-plane
    magnitude ρ = cos(el) ≤ 1, so an error in ρ only ever makes |el| larger (measured 2.6-5.3° for sources
    at −2…+1°: robot seeds 1-2, A5/A2, a tilt 3-4σ off with these rows taken as independent). Those rows'
    elevation errors (each of its std) are therefore also taken as one error they share, which their
    number does not average down."""
    for f, start, n in _kind_blocks(lin, "doa"):
        arr, u = p.doa.arr, p.doa.u
        nv = normals[arr]
        keep = (lin.w[start:start + n] > 0).reshape(-1, 3).all(axis=1) & np.any(nv != 0, axis=1)
        if not keep.any():
            return None
        cos_n = np.einsum("ka,ka->k", nv, u)
        e_el = nv - cos_n[:, None] * u
        e_el /= np.maximum(np.linalg.norm(e_el, axis=1), 1e-12)[:, None]
        e_az = np.cross(u, e_el)
        block = _doa_block(lin, f, start, n)
        r, J, sig = _array_frame_rows(p, lin, f, start, n, block)
        P = _array_frame_prediction(p, lin, f, start, n, block)
        sin_el = np.abs(cos_n)
        corr = factors.get("doa_correlation", np.ones(p.N))
        iso_factor = factors.get("doa", np.ones(p.N))
        G = []
        for i in np.unique(arr[keep]):
            m = np.flatnonzero(keep & (arr == i))
            if len(m) < 3:
                keep[arr == i] = False
                continue
            t_az, t_el = np.einsum("ka,ka->k", e_az[m], r[m]), np.einsum("ka,ka->k", e_el[m], r[m])
            g_az, g_el = np.einsum("ka,kan->kn", e_az[m], J[m]), np.einsum("ka,kan->kn", e_el[m], J[m])
            s, x_az, x_el = sin_el[m], t_az * sig[m], t_el * sig[m]   # natural units (rad)
            for _ in range(2):   # σ_p² (the rotation absorbs 3 of the 2n in-plane residuals) and the floor of sin(el)
                sp2 = float(np.sum(x_az ** 2 + (x_el * s) ** 2)) / max(2 * len(m) - 3, 1)
                s = np.maximum(sin_el[m], np.sqrt(np.sqrt(sp2) / 2.0))
            # each row's own in-plane error² (in its sigma), over the share of it the fit leaves in the residual
            h_az, h_el = (_leverages_along(np.einsum("ka,kan->kn", e, P[m]), g, cov, 3.0 / (2 * len(m)))
                          for e, g in ((e_az[m], g_az), (e_el[m], g_el)))
            c2_az, c2_el = t_az ** 2 / (1.0 - h_az), (t_el * s) ** 2 / (1.0 - h_el)
            # the elevation never below the row's own sigma with its array's factor (what the fit absorbs of a
            # tilt its residuals cannot show); the azimuth is what the array measures best
            var_az = c2_az * corr[i]
            var_el = np.maximum(c2_el * corr[i] / s ** 2, iso_factor[i])
            # a row within FOLD_SIGMAS of its elevation noise of the plane cannot tell the plane's sides apart
            # (a stated hemisphere, or the fold, puts it on one): its elevation may be off by up to twice itself
            el = np.arcsin(np.clip(sin_el[m], 0.0, 1.0))
            near = el < FOLD_SIGMAS * np.sqrt(var_el) * sig[m]
            var_el = var_el + np.where(near, (el / sig[m]) ** 2, 0.0)
            G.append(np.sqrt(var_az)[:, None] * g_az)
            G.append(np.sqrt(var_el)[:, None] * g_el)
            if near.sum() >= 2:   # ... and all of them the same way: one shared error, not averaged down
                G.append(np.sum(np.sqrt(var_el[near])[:, None] * g_el[near], axis=0, keepdims=True))
        rows = np.zeros(len(lin.r), bool)
        rows[start:start + n] = np.repeat(keep, 3)
        return {"rows": rows, "G": np.vstack(G)} if G else None
    return None


# A non-reference array's DOAs share a rotation error of this fraction of the scatter its own rows show about the fit
# (:func:`_row_scatter`). Measured against truth on development seeds (189 arrays of lab, hall, moving, robot,
# lshape, office, mixed 500-509; per array the rotation that best turns its kept DOAs onto the true directions,
# per axis, less its own noise, over its median row sigma): the pooled maximum-likelihood fraction 0.89 (0.90
# fitted on seeds 500-504 alone leaves 0.81-1.15 of the stated sigma RMS per preset on 505-509, 1 array of 79
# beyond 3). The rank correlation of the shared rotation with this scatter is 0.40 (its RMS form: 0.43), with the
# share of rows flagged ``doa_reflection`` 0.22, any flag 0.23, the rows' late-arrival gap 0.03, their number
# -0.08: in box rooms the arrays flagged in most rows share 0.5 of their median row sigma, in the L-shaped rooms
# those with few flags 2.4 (lshape 500's A4: 8.5, its rows scattering at 28 × their sigma)
SHARED_DOA_SCATTER = 0.89
MEDIAN_CHI2_2 = 2 * np.log(2)   # the median of a χ² of 2 degrees (a row's two tangential axes)
# ... and never below this fraction of its median row sigma (an array of a few rows shows little scatter). The
# reference keeps the flag rule (:func:`_shared_fraction`: this fraction, 1.0 with most rows flagged
# ``doa_reflection``): keyed on its scatter, the lab's references (rows at 1.0-1.7 of their sigma, sharing 0-0.6)
# widened every array's std (test_robust's lab error / std RMS 0.46, below its 1 / 1.5); narrowed to the
# measured 0.5 in box rooms, the deployment bench's mixed 507 was ok with an array 3σ off and moving 509 ok with
# one off the bound, unnamed: its term covers errors the model holds nowhere else
SHARED_DOA_FRACTION = 0.25


def shared_doa_rows(p, lin, factors):
    """(M, 3N) dense: each whitened residual's error per unit of a rotation error that all DOA rows of its array
    share, times its std — None without DOA rows. What an array's DOAs have in common is not noise that its
    number of events averages down: a wall reflection 1–2 pulses behind the direct path pulls every DOA of a
    wall array the same way (robot 370's reference: a 0.29° mean error vector over 64 rows), and so does a
    mic-geometry or mounting error. A non-reference array's orientation absorbs such a rotation (its std then
    covers it); the reference's is the gauge, so the whole map turns with it (as far as
    the odometry does not hold it), which rows taken as independent never show. Its std per axis is
    SHARED_DOA_SCATTER × the scatter of the array's own kept rows about the fit (:func:`_row_scatter`: rows that
    scatter widely about the geometry, as behind an L-shaped room's corner, share much of it), at least
    SHARED_DOA_FRACTION × the median of its row sigmas (each with its array's σ² factor ``factors["doa"]``);
    the reference's :func:`_shared_fraction` of that median (the flag rule). A
    measured direction u turned by ω moves the whitened residual B (v − u) / σ by B [u]× ω / σ (B: the row's
    whitening axes)."""
    for f, start, n in _kind_blocks(lin, "doa"):
        keep = (lin.w[start:start + n] > 0).reshape(-1, 3).all(axis=1)
        if not keep.any():
            return None
        arr, u, m = p.doa.arr, p.doa.u, n // 3
        sig = np.broadcast_to(f.row_sigma, n).reshape(m, 3)
        ux = np.zeros((m, 3, 3))
        ux[:, 0, 1], ux[:, 0, 2], ux[:, 1, 2] = -u[:, 2], u[:, 1], -u[:, 0]
        ux -= np.transpose(ux, (0, 2, 1))
        G = np.einsum("kab,kbc->kac", p.doa.axes, ux) / sig[:, :, None]   # (m, 3, 3) whitened, per unit ω
        iso = factors.get("doa", np.ones(p.N))
        row_sd = p.sigma["doa"] * p.doa.scale * np.sqrt(iso[arr])        # each row's sigma (rad)
        refl = np.zeros(m, bool) if p.doa.reflection is None else np.asarray(p.doa.reflection, bool)
        e = np.einsum("kba,kb->ka", p.doa.axes, (f.r * f.row_sigma).reshape(m, 3))   # v − u (rad), array frame
        out = np.zeros((len(lin.r), 3 * p.N))
        for i in np.unique(arr[keep]):
            k = np.flatnonzero(keep & (arr == i))
            sd = float(np.median(row_sd[k])) * (_shared_fraction(refl[k], SHARED_DOA_FRACTION) if i == p.ref
                                                 else SHARED_DOA_FRACTION)
            if i != p.ref:
                sd = max(sd, SHARED_DOA_SCATTER * _row_scatter(e[k], ux[k], p.sigma["doa"] * p.doa.scale[k]))
            rows = start + 3 * k[:, None] + np.arange(3)[None]
            out[rows.ravel(), 3 * i:3 * i + 3] = (sd * G[k]).reshape(-1, 3)
        return out
    return None


def _row_scatter(e, ux, sig):
    """The scatter (rad, per tangential axis) of an array's DOA residuals ``e`` (n, 3) about their best common
    rotation (``ux`` (n, 3, 3): each direction's cross-product matrix): the median of the rows' squared residuals
    over their sigma ``sig`` (n,) read as a Gaussian's (robust to a few rows far off), times their median sigma."""
    A = ux.reshape(-1, 3)
    w = np.linalg.lstsq(A, e.ravel(), rcond=None)[0]
    q = np.sum((e.ravel() - A @ w).reshape(-1, 3) ** 2, axis=1) / sig ** 2
    return float(np.sqrt(np.median(q) / MEDIAN_CHI2_2)) * float(np.median(sig))


# A cone array's (and the reference's DOA) rows flagged ``doa_reflection`` in more than REFLECTION_MAJORITY share
# this fraction of their median row sigma (office, mixed 500-509 against truth: RMS 0.82 over the 23 cone arrays so
# flagged; a cone array's shared rotation is too close to its noise, 26 arrays, to key on its rows' scatter)
SHARED_CONE_FRACTION_REFLECTION = 1.0
REFLECTION_MAJORITY = 0.5


def _shared_fraction(flagged, clear_fraction):
    """The shared rotation's fraction of a cone array's (and the reference's DOA) median row sigma:
    SHARED_CONE_FRACTION_REFLECTION when more than REFLECTION_MAJORITY of its kept rows (``flagged`` (n,) bool)
    were shaped by a reflection close behind the direct path (that reflection's pull), else ``clear_fraction``."""
    return SHARED_CONE_FRACTION_REFLECTION if float(np.mean(flagged)) > REFLECTION_MAJORITY else clear_fraction


# A cone array's (linear board's, pair's) rows share an axis rotation as an array's DOAs do. Measured against truth on
# development seeds (office, mixed 500-509: per cone array the axis rotation that best explains its kept rows' cos
# errors at the true geometry, per axis, less its own noise, over the median row sigma): RMS 0.82 over the 23 with
# most rows flagged ``doa_reflection`` (wall linear boards in the office: 0.98-2.57 where the fit's chi² says it is
# real), 0.27 over the 17 with at most half (the DOAs': 0.95 and 0.44)
SHARED_CONE_FRACTION = SHARED_DOA_FRACTION


def shared_cone_rows(p, lin, st, factors):
    """(M, 3N) dense: as :func:`shared_doa_rows` for the cone rows (linear boards, 2-mic pairs) at the state ``st``:
    each whitened residual's error per unit of an axis rotation error all kept cone rows of its array share, times
    its std — None without cone rows. A wall board's reflection (flagged ``doa_reflection``) pulls all its cones
    the same way: office 505's linear board, axis 6.2° off at 4 of its std, its rows sharing a 4.4° rotation (2.2 ×
    its median row sigma). The std per axis is the median row sigma (the type's, with its array's σ² factor
    ``factors["cone"]``) × :func:`_shared_fraction` (SHARED_CONE_FRACTION when few are flagged). An axis a turned
    by ω moves the row's cos aᵀw (w = Rᵀ n, the source's direction in the array frame) by (a × w)ᵀ ω."""
    for f, start, n in _kind_blocks(lin, "cone"):
        keep = lin.w[start:start + n] > 0
        if not keep.any():
            return None
        arr, ev = p.cone.arr, p.cone.ev
        d = st.s[ev] - st.x[arr]
        w = np.einsum("kba,kb->ka", st.R[arr], d / np.linalg.norm(d, axis=1, keepdims=True))
        sig = np.broadcast_to(f.row_sigma, n)
        G = np.cross(p.cone_axis[arr], w) / sig[:, None]               # (n, 3) whitened, per unit ω
        row_sd = sig * np.sqrt(factors.get("cone", np.ones(p.N))[arr])
        refl = np.zeros(n, bool) if p.cone.reflection is None else np.asarray(p.cone.reflection, bool)
        out = np.zeros((len(lin.r), 3 * p.N))
        for i in np.unique(arr[keep]):
            k = np.flatnonzero(keep & (arr == i))
            out[start + k, 3 * i:3 * i + 3] = float(np.median(row_sd[k])) * _shared_fraction(
                refl[k], SHARED_CONE_FRACTION) * G[k]
        return out
    return None


def _sum_shared(*parts):
    """The sum of the (M, 3N) shared-rotation rows that are not None (None when all are)."""
    parts = [x for x in parts if x is not None]
    return sum(parts[1:], parts[0]) if parts else None


VELOCITY_SCALED_KINDS = {"tdoa_m": "beta", "tdoa_s": "beta", "doa": "t_doa", "cone": "t_doa"}


def velocity_rows(lin, lay, motion):
    """(M, 3K) dense: each whitened residual's error per unit error of the velocity a moving source's
    correction used (one 3-vector per event, ``motion`` a :class:`calib.estimator.motion.MotionNoise`), times
    its std — None without a correction. The error δv_j moves event j's corrected arrivals exactly as a source
    shift of β δv_j moves their times of flight, and its turned DOAs as one of t_doa δv_j, so the whitened
    error is J[:, s_j] (β or t_doa) δv_j: the source's columns of the Jacobian, shared by every array of the
    event (rows not kept, and the odometry's, have none)."""
    if motion is None or not len(lay.s) or np.any(lay.s < 0) or np.any(lay.dv >= 0):
        return None   # (a solve that models the velocity error, ``Problem.motion``, has it in its own J)
    scale, start = np.zeros(len(lin.r)), 0
    for f in lin.factors:
        n = len(f.r)
        key = VELOCITY_SCALED_KINDS.get(f.kind)
        if key is not None:
            scale[start:start + n] = getattr(motion, key)
        start += n
    scale = np.where(lin.w > 0, scale * motion.sigma, 0.0)
    if not np.any(scale):
        return None
    J = lin.J[:, lay.s.ravel()]
    J = J.toarray() if scipy.sparse.issparse(J) else np.asarray(J)
    return J * scale[:, None]


def sandwich_covariance(p, lin, cov, factors, shared=True, normals=None, velocity=None, shared_doa=None):
    """Covariance of the estimate the solve made (weights as stated) under the errors as they are: H⁻¹ B H⁻¹
    with H⁻¹ = ``cov`` (dense, the kept rows' (JᵀJ)⁻¹) and B = Jᵀ C J, C the whitened rows' covariance:
    arrival-sharing TDOA rows through :func:`arrival_rows`, the other rows independent with their array's
    σ² factor (``factors`` {kind: (N,)}, :func:`calib.estimator.variance.covariance_factors`); ``shared``
    False: the TDOA rows independent too (features whose meta.json does not say ``tdoa_shared_arrivals``);
    ``normals`` (N, 3): planar arrays' DOA rows as they err (:func:`planar_doa_rows`); ``velocity``: the
    (M, 3K) rows of a moving source's velocity error (:func:`velocity_rows`), independent of the rest;
    ``shared_doa``: the (M, 3N) rows of each array's common DOA rotation error (:func:`shared_doa_rows`).
    Returns the (n, n) covariance."""
    keep = lin.w > 0
    J = lin.J.toarray() if scipy.sparse.issparse(lin.J) else np.asarray(lin.J)
    f_rows = row_factors(p, lin, factors)
    D = arrival_rows(p, lin, factors) if shared else None
    own = keep.copy()
    planar = None if normals is None else planar_doa_rows(p, lin, normals, factors, cov)
    if planar is not None:
        own &= ~planar["rows"]
    if D is not None:
        own &= np.asarray(abs(D).sum(axis=1)).ravel() == 0
        G = D.T @ J   # (N·K, n): each arrival's error through every row that holds it
        B = G.T @ G
    else:
        B = np.zeros((J.shape[1], J.shape[1]))
    Jo = J[own] * np.sqrt(f_rows[own])[:, None]
    B = B + Jo.T @ Jo
    if planar is not None:
        B = B + planar["G"].T @ planar["G"]
    for extra in (velocity, shared_doa):   # errors shared by rows: an event's velocity, an array's DOAs
        if extra is not None:
            Gv = J.T @ extra   # (n, ·): each shared error through every row it moves
            B = B + Gv @ Gv.T
    out = cov @ B @ cov
    return 0.5 * (out + out.T)


def honest_covariance(p, lin, lay, *, shared=False, normals=None, cov=None, arrays_only=False, motion=None,
                      state=None):
    """The covariance the ``*_std`` columns and calibration.json report, at the final linearisation ``lin``
    (``solver.Linearised``, weights 0 on excluded rows): each (type, array)'s rows with the σ² factor its
    residuals ask for (:func:`calib.estimator.variance.covariance_factors`; below 1 for the direction kinds whose
    residuals say their sigma is wide, ``variance.LOWERED_KINDS``, and for the TDOA kinds of a moving source whose
    velocity error the rows' sigma holds, as that error is then in the covariance as the per-event error it is,
    :func:`velocity_rows`), and for a dense problem the
    TDOA rows' shared arrivals (``shared``, meta.json ``tdoa_shared_arrivals``) and each array's DOA rows' common
    rotation error (:func:`shared_doa_rows`; its cone rows' at the ``state`` of ``lin``, :func:`shared_cone_rows`)
    by :func:`sandwich_covariance`;
    a large (sparse) problem gets the factors alone (:func:`inflated_rows`) in its array block (its
    sources' blocks stay the plain ones: the event blocks would cost a solve per source again). ``cov``: the
    plain (JᵀJ)⁻¹ of the kept rows when already computed; ``normals``: planar arrays' mic-plane normals (:func:`plane_normals`,
    dense problems); ``arrays_only`` as :func:`covariance`; ``motion``: a moving source's velocity error
    (:class:`calib.estimator.motion.MotionNoise`, dense problems: :func:`velocity_rows`)."""
    from .variance import LOWERED_KINDS, covariance_factors   # (variance's stages use this module's neighbours)

    if cov is None:
        cov = covariance(lin.J[lin.w > 0], lay.n, lay, arrays_only)
    if isinstance(cov, np.ndarray):
        velocity = velocity_rows(lin, lay, motion)
        factors = covariance_factors(p, lin, cov, lower=LOWERED_KINDS + (ARRIVAL_KINDS if velocity is not None else ()))
        # the shared rotations' fractions were measured against the rows' stated sigma (SHARED_DOA_FRACTION): not lowered
        stated = covariance_factors(p, lin, cov)
        cone = None if state is None else shared_cone_rows(p, lin, state, stated)
        return sandwich_covariance(p, lin, cov, factors, shared, normals, velocity,
                                   _sum_shared(shared_doa_rows(p, lin, stated), cone))
    factors = covariance_factors(p, lin, cov)
    if not any(np.any(v > 1) for k, v in factors.items() if k in KINDS):
        return cov
    # large problems: the array block with the factors (one more Schur complement); the sources keep theirs
    arrays = covariance(inflated_rows(p, lin, factors), lay.n, lay, arrays_only=True)
    return arrays if arrays_only else cov.with_arrays(arrays)


def cov_diagonal(cov):
    """Diagonal (n,) of a dense covariance or a :class:`BlockCovariance`."""
    return cov.diagonal() if isinstance(cov, BlockCovariance) else np.diag(cov)


def cov_block(cov, ix):
    """Covariance block of the columns ``ix`` of a dense covariance or a :class:`BlockCovariance`."""
    return cov.block(ix) if isinstance(cov, BlockCovariance) else cov[np.ix_(ix, ix)]


def std_from_cov(p, lay, cov):
    """1-σ std per parameter, as arrays keyed like the state (NaN where fixed)."""
    sd = np.sqrt(np.maximum(cov_diagonal(cov), 0.0))

    def pick(idx):
        return np.where(idx >= 0, sd[np.maximum(idx, 0)], np.nan)

    out = {**{a.key: pick(getattr(lay, a.key)) for a in ARRAY_PARAMS}, "s": pick(lay.s), "e": pick(lay.e)}
    # a parameter the data leave undetermined (observability.check_observability) has no std, although
    # the gauge fixes only some of its components
    index = {str(n): i for i, n in enumerate(p.names)}
    for u in p.unobservable:
        out[array_param(u["parameter"]).key][index[u["array"]]] = np.nan
    return out


def state_from_frames(p: Problem, arrays: pd.DataFrame, sources: pd.DataFrame | None = None) -> State:
    """State from arrays/sources DataFrames (e.g. truth), ordered as the problem's arrays/events.

    A per-array parameter without columns, or a scalar one unknown (NaN: offsets, drifts), is at its start
    value; a NaN position stays NaN (an unknown place is not the origin).
    """
    st = empty_state(p)
    ia = _rows_of(arrays["array"], p.names, "array")
    for a in ARRAY_PARAMS:
        if all(c in arrays for c in a.columns):
            v = columns(arrays, a.columns)[ia]
            setattr(st, a.state, Rotation.from_quat(v, scalar_first=True).as_matrix() if a.rotation else
                    (np.nan_to_num(v, nan=a.default) if len(a.components) == 1 else v).reshape(a.shape(p.N)))
    if sources is not None:
        st.s = columns(sources, ("x", "y", "z"))[_rows_of(sources["event"], p.events, "event")]
    return st


def _rows_of(column, keys, what):
    """Row of each key in a frame's column (as ``set_index(column).loc[keys]`` for unique keys; KeyError
    naming the first missing one). Plain lookups: the Monte-Carlo study calls this for every run."""
    row = {}
    for k, v in enumerate(column.tolist()):
        row.setdefault(v, k)
    try:
        return np.array([row[k] for k in np.asarray(keys).tolist()], int)
    except KeyError as exc:
        raise KeyError(f"{what} {exc.args[0]!r} not in the frame") from None


def fisher(p, st, kinds=None):
    """Fisher information JᵀJ of the whitened residuals at ``st`` and its layout."""
    lay = make_layout(p)
    kinds = kinds or active_kinds(p)
    J = linearise(p, st, lay, kinds).J
    return J, lay


def crlb(features: dict[str, Any], truth: dict[str, Any], *, use_tdoa_s: bool = True, emission_sigma: float = 0.0,
         problem: Any = None, state: Any = None) -> dict[str, Any]:
    """Cramér–Rao bound at ground truth.

    Returns dict: ``cov`` (n, n) over the free parameters (a :class:`BlockCovariance` for large problems), ``layout``, ``std`` (per-parameter 1-σ keyed
    like the state: x (N,3) m, rot (N,3) rad, offset (N,) s, drift (N,), s (K,3) m, e (K,) s),
    ``problem`` and ``state`` (the truth state).
    The caller may pass ``problem`` (what ``build_problem(features, use_tdoa_s=use_tdoa_s,
    sigma_emit=emission_sigma)`` gives; not modified) and ``state`` (``state_from_frames`` of the truth for
    a problem with the same arrays and events; copied) when it has them.
    """
    p = build_problem(features, use_tdoa_s=use_tdoa_s, sigma_emit=emission_sigma) if problem is None else problem
    st = state_from_frames(p, truth["arrays"], truth.get("sources")) if state is None else state.copy()
    J, lay = fisher(p, st)
    cov = covariance(J, lay.n, lay)
    return {"cov": cov, "layout": lay, "std": std_from_cov(p, lay, cov), "problem": p, "state": st}


def draw_from_crlb(bound: dict[str, Any], rng: np.random.Generator) -> State:
    """One estimate drawn from N(truth, CRLB) as a state (rotations perturbed on the manifold)."""
    cov = bound["cov"]
    if isinstance(cov, BlockCovariance):
        return retract(bound["state"], bound["layout"], cov.sample(rng))
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    delta = V @ (np.sqrt(np.maximum(w, 0.0)) * rng.standard_normal(len(w)))
    return retract(bound["state"], bound["layout"], delta)


def whiten(J, w):
    """Rows of J scaled by sqrt(w) (IRLS weights), dense or sparse alike."""
    if scipy.sparse.issparse(J):
        return (scipy.sparse.diags(np.sqrt(w)) @ J).tocsr()
    return J * np.sqrt(w)[:, None]


def param_std(J, k):
    """1-σ of parameter k from whitened J: sqrt((JᵀJ)⁻¹_kk) by one Cholesky solve (pinv if singular);
    a sparse J by one sparse LU solve."""
    if scipy.sparse.issparse(J):
        d = np.sqrt(np.asarray(J.multiply(J).sum(axis=0)).ravel())
        d = np.where(d > 0, d, 1.0)
        Js = (J @ scipy.sparse.diags(1.0 / d)).tocsc()
        e = np.zeros(J.shape[1])
        e[k] = 1.0
        x = scipy.sparse.linalg.splu((Js.T @ Js).tocsc()).solve(e)
        return float(np.sqrt(max(x[k], 0.0)) / d[k])
    d = np.linalg.norm(J, axis=0)
    d = np.where(d > 0, d, 1.0)
    Js = J / d
    e = np.zeros(J.shape[1])
    e[k] = 1.0
    try:
        x = scipy.linalg.cho_solve(scipy.linalg.cho_factor(Js.T @ Js), e)
    except np.linalg.LinAlgError:
        x = np.linalg.pinv(Js.T @ Js) @ e
    return float(np.sqrt(max(x[k], 0.0)) / d[k])


def cover_alternative(out, name, displacement, rotvec):
    """Widen array ``name``'s reported uncertainty in ``calibrate``'s output ``out`` (in place) to cover a second
    solution the data do not exclude (``estimator.ambiguity``): the other pose is ``displacement`` (3,, m,
    world axes) and ``rotvec`` (3,, rad, about the array's own axes: R Exp(φ)) away. Its covariance gains
    the outer products d dᵀ and φ φᵀ (the spread of the two solutions: were the other one the truth, its error
    would be within 1σ of that covariance, Mahalanobis dᵀ C⁻¹ d < 1), so each ``*_std`` column becomes
    √(std² + d_c²); a NaN std (a component the data leave undetermined) stays NaN. calibration.json's
    ``covariance`` (``out["array_covariance"]``, when present) gains the same outer products."""
    arrays = out["arrays"]
    k = arrays.index[arrays["array"] == name]
    extra = {"x": np.asarray(displacement, float), "rot": np.asarray(rotvec, float)}
    for key, d in extra.items():
        for c, dc in zip(array_param(key).std_columns, d):
            arrays.loc[k, c] = np.hypot(arrays.loc[k, c].to_numpy(float), dc)
    cov = out.get("array_covariance")
    if cov is None:
        return out
    labels, C = cov
    C = np.array(C, float)
    for key, d in extra.items():
        ix = [labels.index(f"{name}.{c}") if f"{name}.{c}" in labels else -1 for c in array_param(key).components]
        sel = [(j, dc) for j, dc in zip(ix, d) if j >= 0]
        if sel:
            j, v = np.array([s[0] for s in sel]), np.array([s[1] for s in sel])
            C[np.ix_(j, j)] += np.outer(v, v)
    out["array_covariance"] = (labels, C)
    return out
