"""The clock scans' linear algebra at scale (used by :mod:`calib.estimator.clockmodel`).

* :class:`Projector`: the orthogonal projection off the columns of a weighted sparse Jacobian A (rows × n),
  through the Cholesky factor of AᵀA (n × n; no dense rows × n matrix, no QR): residuals, the squared norm of
  a column's projection, and blocks of the hat matrix A (AᵀA)⁻¹ Aᵀ.
* :func:`clock_rows` / :func:`family_scores`: every candidate clock component of one clock (a step at every
  event interval, a hinge at every event time, the quadratic) scored against that clock's own TDOA rows in
  O(rows + candidates) by sorted cumulative sums (a step at τ is 1 on every arrival at or after τ; a hinge is
  (u − τ)⁺): no rows × candidates matrix. The score of a candidate b is (bᵀr)² / |b|², both projected off a
  few columns C (the clock's own array parameters): the local screen of the joint scan. It sees a step as
  the one TDOA-S row it falls in and every later TDOA-M row moving together, a drift change as curvature of
  the TDOA-M rows in time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse

RIDGE = 1e-10   # relative (after Jacobi scaling): directions the rows do not fix (a gauge, a weightless array)
DENSE_PROJECT = 600   # parameters: up to this AᵀA is factored dense, beyond by the solver's Schur complement


class Projector:
    """Projection off the columns of A (CSR or dense, rows × n): P x = x − A (AᵀA)⁻¹ Aᵀ x. ``prior`` (n,): a
    unit prior on some columns (a nuisance of known σ, its columns scaled by it): (AᵀA + diag(prior))⁻¹, as if
    rows [0 I] with zero residual were appended; on A's own rows every quantity is that augmented projection's.

    AᵀA is Jacobi-scaled (unit diagonal; a column no row touches gets 1: it projects out nothing) with a tiny
    ridge (directions the rows do not fix: a gauge) and factored once: dense Cholesky for a small problem, else
    as the solver does (``solver.Schur``: the banded event block eliminated, a dense array block; ``lay`` the
    problem's layout, columns past ``lay.n`` are array-block columns: the clock components)."""

    def __init__(self, A, lay=None, prior=None):
        from .solver import Schur

        self.A = scipy.sparse.csr_matrix(A)
        n = self.A.shape[1]
        H = (self.A.T @ self.A).tocsr()
        if prior is not None:   # (n,) unit-σ prior rows on some columns (a nuisance): AᵀA + diag(prior)
            H = (H + scipy.sparse.diags(np.asarray(prior, float))).tocsr()
        dead = H.diagonal() <= 0
        if dead.any():
            H = H + scipy.sparse.diags(dead.astype(float))
        self.n, self.schur = n, None
        if lay is not None and n > DENSE_PROJECT:
            self.schur = Schur(H, lay).factor(RIDGE)
            return
        Hd = H.toarray()
        self.d = np.sqrt(np.diag(Hd))
        Hs = Hd / self.d[:, None] / self.d[None, :] + RIDGE * np.eye(n)
        self.cho = scipy.linalg.cho_factor(Hs, check_finite=False) if n else None

    def solve(self, Y):
        """(AᵀA)⁻¹ Y for Y (n, q)."""
        Y = np.asarray(Y, float).reshape(self.n, -1)
        if not self.n:
            return Y
        if self.schur is None:
            return scipy.linalg.cho_solve(self.cho, Y / self.d[:, None], check_finite=False) / self.d[:, None]
        sch = self.schur
        z = sch._solve_scaled((Y / sch.d[:, None])[sch.perm])
        x = np.empty_like(z)
        x[sch.perm] = z
        return x / sch.d[:, None]

    def resid(self, X):
        """P X: X (rows,) or (rows, q) off A's columns."""
        X = np.asarray(X, float)
        X2 = X.reshape(len(X), -1)
        return (X2 - self.A @ self.solve(self.A.T @ X2)).reshape(X.shape)

    def explained(self, rows, X):
        """|H x|² = xᵀ A (AᵀA)⁻¹ Aᵀ x for each column x of X (len(rows), q), given on the rows ``rows`` (zero
        elsewhere)."""
        Y = np.asarray(self.A[rows].T @ X).reshape(self.n, -1)
        return np.einsum("ij,ij->j", Y, self.solve(Y))

    def hat(self, R):
        """H_RR = A_R (AᵀA)⁻¹ A_Rᵀ for the row indices R."""
        return self.hat_of(np.arange(self.A.shape[0]))(np.asarray(R))

    def hat_of(self, rows):
        """A function R ↦ H_RR for index sets R into ``rows`` (row indices of A): the rows' scaled and permuted
        part of A is taken once, each call is then numpy on |R| rows (a clock's persistence asks for thousands)."""
        AO = self.A[rows]
        if self.schur is None:
            return lambda R: (np.asarray(AO[R] @ self.solve(AO[R].T.toarray())) if AO[R].nnz
                              else np.zeros((len(R), len(R))))
        sch = self.schur
        Ah = (AO[:, sch.perm] @ scipy.sparse.diags(1.0 / sch.d[sch.perm])).tocsr()
        return lambda R: self._schur_hat(Ah[R].toarray())

    def _schur_hat(self, Ad):
        """H_RR from the Schur blocks for rows Ad (dense, scaled and permuted: array columns first): with the
        array part a, the event part e on the few event parameters T the rows touch and X = H_EE⁻¹ H_EA,
        H_RR = Y S⁻¹ Yᵀ + e (H_EE⁻¹)_TT eᵀ, Y = a − e X_T (a row group costs its rows × the array block)."""
        sch = self.schur
        a, ev = Ad[:, :sch.nA], Ad[:, sch.nA:]
        T = np.flatnonzero(np.any(ev != 0, axis=0))
        e = ev[:, T]
        Y = a - e @ sch.X[T] if len(T) else a
        SY = (scipy.linalg.cho_solve(sch.cho, Y.T, check_finite=False) if sch.cho is not None
              else np.linalg.lstsq(sch.S, Y.T, rcond=None)[0])
        H = Y @ SY
        if len(T):
            band = sch.event_inverse(T[:, None], T[None, :])
            if band is None:
                unit = np.zeros((sch.Hee.shape[0], len(T)))
                unit[T, np.arange(len(T))] = 1.0
                band = sch.lu.solve(unit)[T]
            H = H + e @ band @ e.T
        return H


@dataclass(frozen=True)
class ClockRows:
    """One clock's TDOA rows (the stacked rows it stamps, ``rows``), each as one or two "ends": an arrival at
    time ``U`` (s since t0) entering with sign ``sgn`` (TDOA-M: its event, +1 (−1 for the reference's clock);
    TDOA-S a → b: b with +1, a with −1). ``end_row``: the end's row (index into ``rows``), ``far``: the time of
    its row's later end, ``span``: for an earlier end, its row's u_b − u_a (0 otherwise); ``w``: the rows'
    coefficient (sign / σ, times their robust √weight), ``label``: the rows' array."""
    rows: np.ndarray
    label: np.ndarray
    w: np.ndarray
    U: np.ndarray
    sgn: np.ndarray
    end_row: np.ndarray
    far: np.ndarray
    span: np.ndarray


def clock_rows(p, fs, i, sw):
    """:class:`ClockRows` of clock i (-1: the emitter, every TDOA-S; the reference: its TDOA-S and every TDOA-M,
    negated) over the stacked factors ``fs``, rows with √weight ``sw`` > 0 only."""
    u = p.t
    rows, w, ends, label = [], [], [], []
    start = 0
    for f in fs:
        n = len(f.r)
        sig = np.broadcast_to(f.row_sigma, n)
        if f.kind == "tdoa_s" and len(p.tdoa_s.a) == n:
            mine = np.ones(n, bool) if i < 0 else p.tdoa_s.arr == i
            k = np.flatnonzero(mine & (sw[start:start + n] > 0))
            ua, ub = u[p.tdoa_s.a[k]], u[p.tdoa_s.b[k]]
            ends.append((sum(len(x) for x in rows), ub, ua, k))
            label.append(p.tdoa_s.arr[k])
            rows.append(start + k)
            w.append(sw[start + k] / sig[k])
        elif f.kind == "tdoa_m" and len(p.tdoa_m.ev) == n and i >= 0:
            mine = np.ones(n, bool) if i == p.ref else p.tdoa_m.arr == i
            k = np.flatnonzero(mine & (sw[start:start + n] > 0))
            ends.append((sum(len(x) for x in rows), u[p.tdoa_m.ev[k]], None, k))
            label.append(p.tdoa_m.arr[k])
            rows.append(start + k)
            w.append((-1.0 if i == p.ref else 1.0) * sw[start + k] / sig[k])
        start += n
    U, sgn, er, far, span = [], [], [], [], []
    for off, ub, ua, k in ends:
        idx = off + np.arange(len(k))
        U.append(ub), sgn.append(np.ones(len(k))), er.append(idx), far.append(ub), span.append(np.zeros(len(k)))
        if ua is not None:
            U.append(ua), sgn.append(-np.ones(len(k))), er.append(idx), far.append(ub), span.append(ub - ua)
    cat = (lambda xs, dt=float: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt))
    return ClockRows(cat(rows, int), cat(label, int), cat(w), cat(U), cat(sgn), cat(er, int), cat(far), cat(span))


def subset(cr, keep):
    """The :class:`ClockRows` of the rows where ``keep`` (bool over cr.rows) holds."""
    new = np.cumsum(keep) - 1
    e = keep[cr.end_row]
    return ClockRows(cr.rows[keep], cr.label[keep], cr.w[keep], cr.U[e], cr.sgn[e], new[cr.end_row[e]], cr.far[e],
                     cr.span[e])


def _tail_sums(U, Y, taus):
    """Σ_{ends with U ≥ τ} Y for every τ in taus: (len(taus), q) for Y (len(U), q); U sorted ascending."""
    tail = np.concatenate([np.cumsum(Y[::-1], axis=0)[::-1], np.zeros((1, Y.shape[1]))])
    return tail[np.searchsorted(U, taus, side="left")]


def family_products(cr, X, steps, hinges):
    """Products of the unit-coefficient columns of every candidate with the columns of X (len(cr.rows), q),
    and their squared norms, each column's rows times ``cr.w``: (P (k, q), norms (k,)) for the step times
    ``steps``, then the quadratic, then the hinge knots ``hinges`` (k = len(steps) + 1 + len(hinges))."""
    o = np.argsort(cr.U, kind="stable")
    U, sgn, er, far, span = cr.U[o], cr.sgn[o], cr.end_row[o], cr.far[o], cr.span[o]
    w = cr.w[er]
    q = X.shape[1]
    Xe = X[er] * (sgn * w)[:, None]
    w2 = sgn * w * w
    # the quadratic u²/2: its column on the rows directly
    qcol = np.bincount(er, sgn * 0.5 * U ** 2, minlength=len(cr.rows)) * cr.w
    # steps: Σ over ends at or after τ; hinges (u − τ)⁺: Σ u·y − τ Σ y there; a hinge's squared column is
    # (u_b − τ)² on [u_a, u_b) and (u_b − u_a)² before u_a
    Ps = _tail_sums(U, np.column_stack([Xe, w2]), steps)
    h = np.asarray(hinges, float)
    Th = _tail_sums(U, np.column_stack([Xe * U[:, None], Xe, w2 * far * far, w2 * far, w2,
                                        w * w * span ** 2 * (sgn < 0)]), h)
    Ph = Th[:, :q] - h[:, None] * Th[:, q:2 * q]
    a, b, c, d = Th[:, 2 * q:].T
    nh = a - 2 * h * b + h * h * c + d
    return np.vstack([Ps[:, :q], (qcol @ X)[None, :], Ph]), np.concatenate([Ps[:, q], [qcol @ qcol], nh])


def family_columns(cr, comps):
    """The unit-coefficient columns of components ``comps`` on the clock's rows (len(cr.rows), len(comps)),
    times ``cr.w`` (for the few candidates scored exactly)."""
    from .clockmodel import basis_matrix

    phi = basis_matrix(comps, cr.U) * cr.sgn[:, None]
    out = np.zeros((len(cr.rows), len(comps)))
    np.add.at(out, cr.end_row, phi)
    return out * cr.w[:, None]


def _owners(cr, C):
    """For each column of C (CSC, len(cr.rows) × m): the array whose rows alone it touches, -2 when it touches
    several arrays' (shared), -1 when none."""
    owner = np.full(C.shape[1], -1)
    lab = cr.label[C.indices]
    for j in np.flatnonzero(np.diff(C.indptr)):
        cl = lab[C.indptr[j]:C.indptr[j + 1]]
        owner[j] = cl[0] if np.all(cl == cl[0]) else -2
    return owner


def project_off(cr, C, X):
    """X (len(cr.rows), q) projected off the columns of C (sparse): array by array, then the shared columns."""
    C = scipy.sparse.csc_matrix(C)
    owner = _owners(cr, C)
    X = np.array(X, float).reshape(len(cr.rows), -1)
    Cs = C[:, np.flatnonzero(owner == -2)].toarray()
    for a in np.unique(owner[owner >= 0]):
        rows = cr.label == a
        Ca = C[:, np.flatnonzero(owner == a)][rows].toarray()
        Y = np.column_stack([X[rows], Cs[rows]])
        Y = Y - Ca @ np.linalg.lstsq(Ca, Y, rcond=None)[0]
        X[rows], Cs[rows] = Y[:, :X.shape[1]], Y[:, X.shape[1]:]
    return X - Cs @ np.linalg.lstsq(Cs, X, rcond=None)[0] if Cs.shape[1] else X


def local_scores(cr, C, r, steps, hinges):
    """Each candidate's (χ² drop, coefficient) against the clock's weighted residuals r (on its rows) with both
    projected off the columns C (sparse, len(cr.rows) × m): the drop (bᵀr)²/|b|² and the coefficient −bᵀr/|b|²
    (residual = model − data). C's columns that touch the rows of one array only are projected out array by
    array (the reference's clock: every array's TDOA-M, and each array's own parameters on them), the rest
    (shared) after them (Frisch–Waugh); no rows × m dense matrix."""
    C = scipy.sparse.csc_matrix(C)
    owner = _owners(cr, C)
    shared = np.flatnonzero(owner == -2)
    Cs = C[:, shared].toarray()
    P, nb = family_products(cr, np.column_stack([r, Cs]), steps, hinges)
    num, den, Ps = P[:, 0], nb.copy(), P[:, 1:]
    Csr, CsCs = Cs.T @ r, Cs.T @ Cs
    for a in np.unique(owner[owner >= 0]):
        rows = cr.label == a
        Ca = C[:, np.flatnonzero(owner == a)][rows].toarray()
        G = np.linalg.pinv(Ca.T @ Ca)
        Pa, _ = family_products(subset(cr, rows), Ca, steps, hinges)
        ra, Sa = r[rows], Cs[rows]
        PG, Car, CaS = Pa @ G, Ca.T @ ra, Ca.T @ Sa
        num = num - PG @ Car
        den = den - np.einsum("ij,ij->i", PG, Pa)
        Ps = Ps - PG @ CaS
        Csr = Csr - CaS.T @ (G @ Car)
        CsCs = CsCs - CaS.T @ (G @ CaS)
    if len(shared):
        Gs = np.linalg.pinv(CsCs)
        num = num - Ps @ (Gs @ Csr)
        den = den - np.einsum("ij,jk,ik->i", Ps, Gs, Ps)
    ok = den > 1e-12 * np.maximum(nb, 1e-300)
    value = np.where(ok, -num / np.where(ok, den, 1.0), 0.0)
    return np.where(ok, num * num / np.where(ok, den, 1.0), 0.0), value, np.where(ok, den, 0.0)
