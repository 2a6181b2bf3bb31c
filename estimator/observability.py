"""Observability: can the data determine every free parameter? (Rank of the Fisher information.)

Counting checks first (DOAs and TDOA-Ms per array, the spread of the path), then the smallest singular value
of the column-normalised Jacobian Jn = J D⁻¹ (σ² = eigenvalues of Hn = JnᵀJn; with unit columns the test
σ_min < 1e-6 is far above the ~1e-8 that double precision resolves through Hn). Small problems take the
eigen-decomposition of the dense Hn; large ones never form it: the event block of Hn is factorised sparse,
the array block reduced by the Schur complement S, and the smallest eigenvalue of Hn found by Lanczos
iteration on Hn⁻¹ (solves with those factors).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from .init import ObservabilityError
from .solver import Schur, linearise

# Jn's smallest singular value below this (absolute; Jn has unit columns) means rank deficient.
ABS_SINGULAR = 1e-6
# Lanczos tolerance on the largest eigenvalue of Hn⁻¹: the decision compares it with 1e12, so three
# significant digits are plenty.
LANCZOS_TOL = 1e-3


def check_observability(p, lay, kinds, st, rel_tol=1e-9, dense=None):
    """Raise ObservabilityError naming what the data cannot determine (rank of the Fisher information).

    ``dense`` as in :func:`calib.estimator.solver.linearise` (None: by problem size).
    """
    _check_counts(p)
    J = linearise(p, st, lay, kinds, dense=dense).J
    sparse = scipy.sparse.issparse(J)
    norms = np.sqrt(np.asarray(J.multiply(J).sum(axis=0)).ravel()) if sparse else np.linalg.norm(J, axis=0)
    if np.any(norms == 0):
        k = int(np.flatnonzero(norms == 0)[0])
        raise ObservabilityError(f"{describe_param(p, lay, k)} is not touched by any measurement")
    if sparse:
        s_min, s_max, v = _weakest_direction_sparse(J, lay)
    else:  # eigen-decomposition of the small n × n matrix JnᵀJn: σ² = its eigenvalues (resolves σ ≥ 1e-7)
        Jn = J / norms
        lam, V = np.linalg.eigh(Jn.T @ Jn)
        s_min, s_max, v = np.sqrt(max(lam[0], 0.0)), np.sqrt(lam[-1]), V[:, 0]
    if s_min < rel_tol * s_max * np.sqrt(J.shape[1]) or s_min < ABS_SINGULAR:
        v = np.abs(v)
        worst = np.argsort(v)[::-1][:3]
        what = ", ".join(describe_param(p, lay, int(k)) for k in worst if v[k] > 0.1 * v.max())
        s = st.s - st.s.mean(0)
        sv = np.linalg.svd(s, compute_uv=False)
        hint = " (all sources are nearly collinear)" if sv[1] < 1e-3 * max(sv[0], 1e-12) else ""
        raise ObservabilityError(f"the data cannot determine {what}{hint}")


def _check_counts(p):
    """Per-array DOA / TDOA-M counts and the spread of the source path (cheap, named errors)."""
    K = p.K
    # arrays with DOAs for fewer than 2 events are not refused: their orientation is left out of the
    # estimate and reported as undetermined (calibrate.undetermined_parameters)
    nt = np.bincount(p.tdoa_m.arr, minlength=p.N)
    for i in range(p.N):
        if i == p.ref:
            continue
        if nt[i] < 1:
            raise ObservabilityError(f"array {p.names[i]} has no TDOA-M: its clock offset is undetermined")
    o = p.odom - p.odom.mean(0)
    sv = np.linalg.svd(o, compute_uv=False)
    if sv[1] / np.sqrt(K) < max(2.0 * p.sigma["odometry"], 1e-3 * sv[0] / np.sqrt(K)):
        raise ObservabilityError(
            "all sources are (nearly) collinear (odometry spread across the path "
            f"{100 * sv[1] / np.sqrt(K):.1f} cm): each array's rotation about that line is unobservable")


def _weakest_direction_sparse(J, lay):
    """Smallest and largest singular value of Jn = J D⁻¹ and the right singular vector (n,) of the smallest.

    Uses Hn = JnᵀJn = the Jacobi-scaled normal matrix of :class:`Schur` (σ² = eigenvalues of Hn).
    """
    H = (J.T @ J).tocsr()
    n = H.shape[0]
    sch = Schur(H, lay)
    Hn = scipy.sparse.diags(1.0 / sch.d) @ H @ scipy.sparse.diags(1.0 / sch.d)
    lam_max = float(scipy.sparse.linalg.eigsh(Hn, k=1, which="LA", v0=np.ones(n), return_eigenvectors=False)[0])

    def unpermute(z):
        out = np.empty_like(z)
        out[sch.perm] = z
        return out

    try:
        sch.factor(0.0)
    except RuntimeError:  # the event block alone is singular: name its weakest source
        return 0.0, np.sqrt(lam_max), _weakest_event(sch, lay)
    w, V = np.linalg.eigh(sch.S) if sch.nA else (np.array([np.inf]), np.zeros((0, 1)))
    if w[0] < ABS_SINGULAR ** 2:  # the reduced array system is singular: H is too, along (v_A, −X v_A)
        z = np.concatenate([V[:, 0], -sch.X @ V[:, 0]])
        return np.sqrt(max(w[0], 0.0)), np.sqrt(lam_max), unpermute(z / np.linalg.norm(z))
    op = scipy.sparse.linalg.LinearOperator((n, n), matvec=sch._solve_scaled, dtype=float)
    mu, U = scipy.sparse.linalg.eigsh(op, k=1, which="LA", v0=np.ones(n), tol=LANCZOS_TOL)
    return 1.0 / np.sqrt(max(float(mu[0]), 1e-300)), np.sqrt(lam_max), unpermute(U[:, 0])


def _weakest_event(sch, lay):
    """Direction (n,) of the weakest source: smallest eigenvector of its 3 × 3 block of the scaled H_EE."""
    nA = sch.nA
    pos = np.full(lay.n, -1)
    pos[sch.perm[nA:]] = np.arange(sch.Hee.shape[0])
    best, out = np.inf, np.zeros(lay.n)
    for cols in lay.s:
        if np.any(cols < 0):
            continue
        e = pos[cols]
        w, V = np.linalg.eigh(sch.Hee[e][:, e].toarray())
        if w[0] < best:
            best, out = w[0], np.zeros(lay.n)
            out[cols] = V[:, 0]
    return out


def describe_param(p, lay, k):
    """Words for parameter column ``k`` of layout ``lay`` (e.g. "the orientation of array A3")."""
    for key, label in (("x", "position"), ("rot", "orientation"), ("offset", "offset"), ("drift", "drift")):
        hit = np.argwhere(getattr(lay, key).reshape(p.N, -1) == k)
        if hit.size:
            return f"the {label} of array {p.names[hit[0, 0]]}"
    hit = np.argwhere(lay.s == k)
    if hit.size:
        return f"the position of source (event {p.events[hit[0, 0]]})"
    hit = np.argwhere(lay.e == k)
    if hit.size:
        return f"the emission time of event {p.events[hit[0, 0]]}"
    return f"parameter {k}"
