"""Levenberg–Marquardt on the product manifold (R^n × SO(3)^N) with an optional robust loss.

The robust loss applies to the factors flagged ``robust`` (the TDOAs) and is minimised by iteratively
reweighted least squares inside LM: each iteration linearises, weights each robust residual by
ρ'(r)/(2r) and solves the damped, Jacobi-scaled normal equations. Deterministic: no random restarts.
Small problems solve them dense; large ones with a sparse Jacobian and a Schur complement (:class:`Schur`).
"""
from __future__ import annotations

import dataclasses
import threading
from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from .factors import Jacobian, evaluate
from .problem import retract


def rho(r, loss, k):
    """Robust cost ρ(r) (so that ρ(r) = r² near 0) and IRLS weight ρ'(r)/(2r), elementwise."""
    if loss is None or loss == "linear":
        return r * r, np.ones(r.shape, r.dtype)   # (np.ones_like's value without its Python-level wrapper)
    if loss == "huber":
        a = np.abs(r)
        small = a <= k
        return np.where(small, r * r, 2 * k * a - k * k), np.where(small, 1.0, k / np.maximum(a, 1e-300))
    if loss == "cauchy":
        z = (r / k) ** 2
        return k * k * np.log1p(z), 1.0 / (1.0 + z)
    raise ValueError(f"unknown loss {loss!r}")


# Up to this many free parameters the normal equations are formed and solved dense (LAPACK on a small
# matrix beats any sparse bookkeeping: the paper's 5 arrays x 14 events have 75); above it the Jacobian
# is assembled sparse and the LM step eliminates the event (source) blocks by a Schur complement.
DENSE_MAX_PARAMS = 300


def use_dense(lay):
    """Whether a problem with layout ``lay`` takes the dense path (see ``DENSE_MAX_PARAMS``)."""
    return lay.n <= DENSE_MAX_PARAMS


def stack_jacobians(Js, n, dense):
    """Stack the factors' Jacobians (each a ``factors.Jacobian``, a dense array or scipy.sparse matrix).

    Returns the (M, n) Jacobian: a dense array if ``dense`` else a ``scipy.sparse.csr_matrix`` (32-bit
    indices where they fit; each factor's rows built in place, :func:`_csr_parts`, without a COO copy).
    """
    M = sum(J.shape[0] for J in Js)
    if dense:  # one pass over all entries; bincount sums any duplicates
        rows, cols, vals, off = [], [], [], 0
        for J in Js:
            for r, c, v in _chunks(J):
                rows.append(np.asarray(r, np.int64) + off), cols.append(c), vals.append(v)
            off += J.shape[0]
        if not rows:
            return np.zeros((M, n))
        rows, cols, vals = (np.concatenate(z) for z in (rows, cols, vals))
        return np.bincount(rows * n + cols, weights=vals, minlength=M * n).reshape(M, n)
    parts = [_csr_parts(J, n) for J in Js]
    nnz = sum(len(d) for _, _, d in parts)
    itype = np.int32 if max(nnz, n, M) < np.iinfo(np.int32).max else np.int64
    indptr, off = [np.zeros(1, itype)], 0
    for ptr, _, _ in parts:
        indptr.append((ptr[1:] + off).astype(itype))
        off += int(ptr[-1])
    data = np.concatenate([d for _, _, d in parts]) if parts else np.zeros(0)
    indices = np.concatenate([c.astype(itype, copy=False) for _, c, _ in parts]) if parts else np.zeros(0, itype)
    return scipy.sparse.csr_matrix((data, indices, np.concatenate(indptr)), shape=(M, n))


def _chunks(J):
    """A factor Jacobian's (rows, cols, vals) chunks (a ``factors.Jacobian``'s own, else from COO)."""
    if isinstance(J, Jacobian):
        return J.chunks
    C = scipy.sparse.coo_matrix(J)
    return [(C.row, C.col, C.data)]


def _csr_parts(J, n):
    """(indptr, indices, data) of one factor's Jacobian in CSR order. One chunk whose rows are in order (every
    built-in factor's) is used as it is: its (row, col) pairs are distinct; otherwise the rows are ordered by a
    stable sort and duplicates summed."""
    chunks = _chunks(J)
    m = J.shape[0]
    if len(chunks) == 1 and np.all(np.diff(chunks[0][0]) >= 0):
        r, c, v = chunks[0]
    else:
        if not chunks:
            return np.zeros(m + 1, np.int64), np.zeros(0, np.int64), np.zeros(0)
        r, c, v = (np.concatenate(z) for z in zip(*chunks))
        C = scipy.sparse.csr_matrix((v, (r, c)), shape=(m, n))
        C.sum_duplicates()
        return C.indptr, C.indices, C.data
    ptr = np.zeros(m + 1, np.int64)
    np.cumsum(np.bincount(r, minlength=m), out=ptr[1:])
    return ptr, c, np.asarray(v, float)


class Linearised(NamedTuple):
    """The stacked factors at one state: whitened residuals r (M,), Jacobian J (M, n; dense or CSR), IRLS
    weights w (M,), cost ½ Σ ρ(r) and the factors in stacking order (their ``J`` None: its rows are in J, not
    kept twice)."""
    r: np.ndarray
    J: object
    w: np.ndarray
    cost: float
    factors: list


def linearise(p, st, lay, kinds, loss=None, k=3.0, mask=None, dense=None) -> Linearised:
    """Stack the factors: residuals r, Jacobian J, IRLS weights w, per-residual kind labels and cost.

    ``mask`` maps factor kind → boolean array over that factor's residuals (False = excluded outlier).
    ``dense``: J as a dense (M, n) array (True), a ``scipy.sparse.csr_matrix`` (False) or chosen by size
    (None, see :func:`use_dense`).
    """
    dense = use_dense(lay) if dense is None else dense
    fs, J = _stacked(p, st, lay, kinds, dense)
    r_all, w_all, cost = [], [], 0.0
    for f in fs:
        r = f.r
        c, w = rho(r, loss if f.robust else None, k)
        if mask is not None and f.kind in mask:  # excluded residuals: zero residual, weight and cost
            keep = mask[f.kind]
            r, c, w = np.where(keep, r, 0.0), np.where(keep, c, 0.0), np.where(keep, w, 0.0)
        cost += 0.5 * float(np.add.reduce(c))   # np.sum's value (the same pairwise sum), without its wrapper
        r_all.append(r)
        w_all.append(w)
    return Linearised(np.concatenate(r_all), J, np.concatenate(w_all), cost, fs)


_last = threading.local()   # .entry: the last sparse linearisation (problem, layout, kinds, state, factors, J)


def forget_linearisation():
    """Drop the kept linearisation (:func:`_stacked`): ``calibrate`` calls this when it returns, so a finished
    large problem's Jacobian (~200 MB at 100 arrays × 5000 events) is not held until the next solve."""
    _last.entry = None


def _stacked(p, st, lay, kinds, dense):
    """The factors at ``st`` (their ``J`` None) and their stacked Jacobian. A large (sparse) problem's last
    ones are kept and returned again for the same problem, layout, kinds and state values: the outlier
    removal linearises each state its solve ends on three times (the solve's last step, the statistics, the
    next solve's start), and only the mask and the weights differ, which are applied afterwards. Nothing
    returned is changed in place by its users."""
    kinds = tuple(kinds)
    hit = None if dense else getattr(_last, "entry", None)
    if hit is not None and hit[0] is p and hit[1] is lay and hit[2] == kinds and \
            hit[3].keys() == vars(st).keys() and all(np.array_equal(v, getattr(st, f)) for f, v in hit[3].items()):
        return hit[4], hit[5]
    fs = evaluate(p, st, lay, kinds)
    J = stack_jacobians([f.J for f in fs], lay.n, dense)
    fs = [dataclasses.replace(f, J=None) for f in fs]
    if not dense:
        _last.entry = (p, lay, kinds, {f: np.array(v) for f, v in vars(st).items()}, fs, J)
    return fs, J


def cost_of(p, st, lay, kinds, loss=None, k=3.0, mask=None):
    """½ Σ ρ(r) at ``st``."""
    cost = 0.0
    for f in evaluate(p, st, lay, kinds):
        keep = np.ones(len(f.r), bool) if mask is None or f.kind not in mask else mask[f.kind]
        c, _ = rho(np.where(keep, f.r, 0.0), loss if f.robust else None, k)
        cost += 0.5 * float(np.sum(np.where(keep, c, 0.0)))
    return cost


def scale_rows(J, w):
    """diag(w) @ J for a CSR matrix, by scaling its stored values (no sparse product)."""
    out = J.copy()
    out.data *= np.repeat(w, np.diff(J.indptr))
    return out


def normal_equations(J, w, r):
    """H = Jᵀ W J and g = Jᵀ W r (dense arrays, or H sparse CSR when J is sparse)."""
    if scipy.sparse.issparse(J):
        J = scipy.sparse.csr_matrix(J)
        return (J.T.tocsr() @ scale_rows(J, w)).tocsr(), J.T @ (w * r)
    Jw = J * w[:, None]
    return J.T @ Jw, Jw.T @ r


def event_columns(lay):
    """Parameter columns of the per-event unknowns (source position, emission correction), event by event.

    In this order the event block of JᵀJ is banded: events couple only to their neighbours in time
    (odometry, TDOA-S between consecutive events, the emission prior).
    """
    cols = np.column_stack([lay.s, lay.dv, lay.e[:, None]]).ravel()   # (dv: a moving source's velocity errors)
    return cols[cols >= 0]


# The event block is factorised as a band matrix (LAPACK banded Cholesky) when its half-bandwidth is at
# most this; beyond (TDOA-S between events far apart in time) by sparse LU.
BAND_MAX = 64


class _BandedSPD:
    """Banded Cholesky of a sparse SPD matrix A + lam I (upper band storage), with a SuperLU-like solve."""

    def __init__(self, A, lam, u):
        C = A.tocoo()
        C.sum_duplicates()
        m = C.row <= C.col
        ab = np.zeros((u + 1, A.shape[0]))
        ab[u + C.row[m] - C.col[m], C.col[m]] = C.data[m]
        ab[u] += lam
        self.u = u
        self.cb = scipy.linalg.cholesky_banded(ab, check_finite=False)

    def solve(self, b):
        return scipy.linalg.cho_solve_banded((self.cb, False), b, check_finite=False)

    def inverse_band(self):
        """The entries of (A + lam I)⁻¹ = Z within the band, ``Zb[i, k] = Z[i, i + k]`` (n, u + 1), by the
        Takahashi recurrence on U (A + lam I = UᵀU; U Z = U⁻ᵀ is lower triangular with diagonal 1/U_ii):
        Z_ij = (δ_ij / U_ii − Σ_{k=i+1}^{i+u} U_ik Z_kj) / U_ii, rows from the last up, each from the (u, u)
        window of Z below it. O(n u²), where reading them off by solves costs O(n² u)."""
        cb, u = self.cb, self.u
        n = cb.shape[1]
        Zb = np.zeros((n, u + 1))
        W = np.zeros((0, 0))   # Z[i+1 : i+1+m, i+1 : i+1+m]
        for i in range(n - 1, -1, -1):
            m = min(u, n - 1 - i)
            uii = cb[u, i]
            urow = cb[u - np.arange(1, m + 1), i + np.arange(1, m + 1)]   # U[i, i+1 : i+1+m]
            z = -(urow @ W) / uii
            zii = (1.0 / uii - urow @ z) / uii
            Zb[i, 0], Zb[i, 1:m + 1] = zii, z
            k = min(u, n - i)   # the next row's window: this row and column, then the top of this window
            W, Wn = np.empty((k, k)), W
            if k:
                W[0, 0], W[0, 1:], W[1:, 0], W[1:, 1:] = zii, z[:k - 1], z[:k - 1], Wn[:k - 1, :k - 1]
        return Zb

    def half_solve(self, b):
        """U⁻ᵀ b (A + lam I = UᵀU): one of the two triangular solves, so that bᵀ (A + lam I)⁻¹ b = |U⁻ᵀ b|²."""
        x, info = scipy.linalg.lapack.dtbtrs(self.cb, b, uplo="U", trans="T")
        if info != 0:
            raise np.linalg.LinAlgError(f"dtbtrs: info {info}")
        return x


def _factor_spd(A, lam):
    """Factor of the sparse SPD matrix A + lam I with a ``solve(b)`` method (banded Cholesky or SuperLU).

    Raises RuntimeError if it is singular.
    """
    C = A.tocoo()
    u = int(np.max(np.abs(C.col - C.row), initial=0))
    if u <= BAND_MAX:
        try:
            return _BandedSPD(A, lam, u)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            pass  # not numerically positive definite: let the pivoting LU decide
    A = (A + lam * scipy.sparse.identity(A.shape[0], format="csc")).tocsc()
    return scipy.sparse.linalg.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                    options={"SymmetricMode": True})


class Schur:
    """The Jacobi-scaled symmetric system H (n, n) split into array (A) and event (E) parameters.

    ``factor(lam)`` prepares (H + lam diag H) for solving by eliminating the event block (bundle-adjustment
    style): the event block H_EE is banded (each event couples to its neighbours through odometry and
    TDOA-S only) and factorised as a band matrix (or by SuperLU); the reduced array system S = H_AA − H_AE H_EE⁻¹ H_EA is
    small and dense. Scaling by d = sqrt(diag H) is the same Jacobi scaling as the dense path.
    """

    def __init__(self, H, lay):
        # (no sum_duplicates: sorting a product's indices costs ~0.5 s per step at 100 arrays x 5000 events;
        # the column/row selections, the diagonal and toarray below read unsorted or repeated entries alike)
        H = scipy.sparse.csr_matrix(H)
        n = H.shape[0]
        ev = event_columns(lay)
        ar = np.setdiff1d(np.arange(n), ev)
        self.perm, self.nA = np.concatenate([ar, ev]), len(ar)
        self.d = np.sqrt(np.maximum(H.diagonal(), 1e-300))
        # the three blocks by scipy's row/column selection (C loops), scaled afterwards: the dense blocks by
        # the outer product of 1/d, the banded event block entry-wise (the same products as scaling first)
        inv_d = 1.0 / self.d
        inv_a, inv_e = inv_d[ar], inv_d[ev]
        HA = H[:, ar]
        self.Haa = HA[ar].toarray() * np.outer(inv_a, inv_a)
        self.Hea = HA[ev].toarray() * np.outer(inv_e, inv_a)
        Hee = H[ev][:, ev]
        Hee.data *= np.repeat(inv_e, np.diff(Hee.indptr)) * inv_e[Hee.indices]
        self.Hee = Hee.tocsc()

    def factor(self, lam=0.0):
        """Factorise Hs + lam I (Hs the scaled H). Raises RuntimeError if the event block is singular.

        With a banded Cholesky UᵀU of the event block, S = H_AA − ZᵀZ with Z = U⁻ᵀ H_EA: one triangular solve
        of the nA columns and a symmetric product, half the work of forming X = H_EE⁻¹ H_EA (:attr:`X`, formed
        only when asked for)."""
        nE = self.Hee.shape[0]
        self._X = None
        if nE:
            self.lu = _factor_spd(self.Hee, lam)
            if isinstance(self.lu, _BandedSPD) and self.nA:
                Z = self.lu.half_solve(self.Hea)
                reduction = Z.T @ Z
            else:
                reduction = self.Hea.T @ self.X
        else:
            self.lu, self._X, reduction = None, np.zeros((0, self.nA)), 0.0
        self.S = self.Haa + lam * np.eye(self.nA) - reduction
        try:
            self.cho = scipy.linalg.cho_factor(self.S, check_finite=False)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            self.cho = None
        return self

    def event_inverse(self, a, b):
        """Entries (a, b) of the event block's inverse (H_EE + lam I)⁻¹ (scaled; positions in the event block,
        integer arrays of one shape), read off its band (:meth:`_BandedSPD.inverse_band`); None when the event
        block was not factorised as a band or a pair lies outside it."""
        if not isinstance(self.lu, _BandedSPD):
            return None
        lo, k = np.minimum(a, b), np.abs(a - b)
        if k.size and k.max() > self.lu.u:
            return None
        if getattr(self, "_band_of", None) is not self.lu:
            self._band, self._band_of = self.lu.inverse_band(), self.lu
        return self._band[lo, k]

    @property
    def X(self):
        """H_EE⁻¹ H_EA (scaled, with the damping of the last :meth:`factor`), (nE, nA)."""
        if self._X is None:
            self._X = self.lu.solve(self.Hea) if self.nA else np.zeros((self.Hee.shape[0], 0))
        return self._X

    def _solve_scaled(self, b):
        """z solving (Hs + lam I) z = b in the permuted, scaled variables (b (nA + nE,) or (·, k))."""
        bA, bE = b[:self.nA], b[self.nA:]
        y = self.lu.solve(bE) if self.lu is not None else bE
        rhs = bA - self.Hea.T @ y
        if self.cho is not None:
            zA = scipy.linalg.cho_solve(self.cho, rhs, check_finite=False)
        else:
            zA = np.linalg.lstsq(self.S, rhs, rcond=None)[0]
        back = self.X @ zA if self._X is not None or self.lu is None else self.lu.solve(self.Hea @ zA)
        return np.concatenate([zA, y - back])

    def solve(self, b):
        """x solving (H + lam diag H) x = b, b (n,) in the original parameter order."""
        z = self._solve_scaled((b / self.d)[self.perm])
        x = np.empty_like(z)
        x[self.perm] = z
        return x / self.d


def cholesky_solve(A, b):
    """x solving A x = b for symmetric positive definite A (Cholesky); None when A is not positive definite."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(A, check_finite=False), b, check_finite=False)
    except np.linalg.LinAlgError:
        return None


def _solve_damped(H, g, lam):
    """Dense LM step: −(H + lam diag H)⁻¹ g via Cholesky of the Jacobi-scaled matrix (lstsq if singular)."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    A = Hs + lam * np.eye(len(d))
    x = cholesky_solve(A, g / d)
    if x is None:   # not positive definite (or a LAPACK argument error): least squares
        x = np.linalg.lstsq(A, g / d, rcond=None)[0]
    return -x / d


# After an accepted step the damping falls by 1 − (2ρ − 1)³ (Nielsen; ρ = actual / predicted decrease), at most
# by this factor (Nielsen's 1/3). A faster fall (1e-3: 12 → 4 final iterations at 100 × 5000) let the robust
# solve of a session with another session's odometry or emission times run off to 200 km / 1e83 m, written to
# arrays.csv beyond what calib's own reader accepts: kept at 1/3.
LAM_DROP = 1.0 / 3.0


def levenberg_marquardt(p, st, lay, kinds, *, loss=None, k=3.0, mask=None, max_iter=200, rtol=1e-12,
                        lam0=1e-4, dense=None):
    """Minimise ½ Σ ρ(r) over the free parameters of ``lay``. Returns (state, info).

    ``dense`` chooses the linear algebra (True: dense Cholesky; False: sparse Jacobian and Schur
    complement on the event blocks; None: by size, :func:`use_dense`); both take the same steps.
    """
    if lay.n == 0:
        return st, {"iterations": 0, "cost": cost_of(p, st, lay, kinds, loss, k, mask), "converged": True,
                    "reason": "no free parameters"}
    dense = use_dense(lay) if dense is None else dense
    lam, nu = lam0, 2.0
    r, J, w, cost = linearise(p, st, lay, kinds, loss, k, mask, dense=dense)[:4]
    reason, it = "max_iter", 0
    for it in range(1, max_iter + 1):
        H = system = None   # (the previous iteration's, released before the new ones are formed)
        H, g = normal_equations(J, w, r)
        diag = np.diag(H) if dense else H.diagonal()
        if (np.abs(g) / np.sqrt(np.maximum(diag, 1e-300))).max() < 1e-10 * max(1.0, np.sqrt(cost)):
            reason = "gradient"
            break
        system = None if dense else Schur(H, lay)
        accepted = False
        for _ in range(30):
            step = _solve_damped(H, g, lam) if dense else system.factor(lam).solve(-g)
            pred = -(step @ g) - 0.5 * step @ (H @ step)   # the decrease the quadratic model predicts
            if 0 < pred <= rtol * max(cost, 1e-30) and it > 1:
                # converged: after a first step, one predicted to lower the cost by less than the tolerance
                # is not evaluated (it would move the state by ~sqrt(2 rtol cost) in whitened units)
                reason = "cost"
                break
            cand = retract(st, lay, step)
            if all(np.array_equal(v, getattr(st, f)) for f, v in vars(cand).items()):
                # the damped step no longer moves the state (it is below the parameters' rounding): it
                # cannot lower the cost, and more damping only shrinks it further
                break
            r2 = J2 = None   # (a rejected candidate's, released first)
            r2, J2, w2, cost2 = linearise(p, cand, lay, kinds, loss, k, mask, dense=dense)[:4]
            ratio = (cost - cost2) / pred if pred > 0 else -1.0
            if cost2 < cost and np.isfinite(cost2):
                accepted = True
                break
            if pred <= rtol * max(cost, 1e-30):
                # rejected, and the model predicted a decrease below the tolerance: a more damped step
                # predicts even less (at a minimum, rounding decides whether one is accepted): converged
                reason = "cost"
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            reason = "no decrease" if reason != "cost" else reason
            break
        lam *= max(LAM_DROP, 1.0 - (2.0 * ratio - 1.0) ** 3) if ratio > 0 else 2.0
        nu = 2.0
        dec = cost - cost2
        st, r, J, w, cost = cand, r2, J2, w2, cost2
        if dec <= rtol * max(cost, 1e-30):
            reason = "cost"
            break
    # "no decrease": no damped step lowers the cost any more, i.e. a numerical minimum.
    return st, {"iterations": it, "cost": cost, "converged": reason != "max_iter", "reason": reason}
