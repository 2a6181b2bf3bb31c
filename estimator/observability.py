"""Observability: what can the data determine? (Rank of the Fisher information, per parameter.)

A counting check first (the spread of the path), then the smallest singular value
of the column-normalised Jacobian Jn = J D⁻¹ (σ² = eigenvalues of Hn = JnᵀJn; with unit columns the test
σ_min < 1e-6 is far above the ~1e-8 that double precision resolves through Hn). Small problems take the
eigen-decomposition of the dense Hn; large ones never form it: the event block of Hn is factorised sparse,
the array block reduced by the Schur complement S, and the smallest eigenvalue of Hn found by Lanczos
iteration on Hn⁻¹ (solves with those factors). Array parameters moved by a null direction are reported
undetermined and left out of the solve (:func:`check_observability`); the rest is calibrated.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from calib.tables import ARRAY_PARAMS

from .init import ObservabilityError
from .solver import Schur, linearise

# Jn's smallest singular value below this (absolute; Jn has unit columns) means rank deficient.
ABS_SINGULAR = 1e-6
# Lanczos tolerance on the largest eigenvalue of Hn⁻¹: the decision compares it with 1e12, so three
# significant digits are plenty.
LANCZOS_TOL = 1e-3


# A column whose weight in a null direction of Jn is at least this fraction of the largest weight is
# part of what the data do not determine (null vectors of a missing measurement are confined to the
# columns it would have touched; other columns get only round-off).
NULL_SUPPORT = 0.02


def check_observability(p, lay, kinds, st, rel_tol=1e-9, dense=None):
    """Determine what the data determine (rank of the Fisher information), per parameter.

    Each null direction of the column-normalised Jacobian (the weakest one, found again after each fix)
    names the parameters it moves (weight >= NULL_SUPPORT of its largest): they are undetermined. An array
    parameter among them (the largest) is then left out of the solve (``fixed_cols``, kept at its
    initial value, NaN std) and the check repeated, so everything else is calibrated: parameters outside
    every null direction are determined whatever the fixed values. Returns a new problem (``p`` is not
    changed) with those ``fixed_cols`` and ``unobservable``: one entry per (array, parameter):
    {"parameter", "array", "reason"} (report.json ``undetermined``). Raises
    ObservabilityError when a null direction moves no non-reference array parameter (e.g. sources only),
    or on the counting checks (collinear source path). ``lay`` is the full layout (recomputed here).
    ``dense`` as in :func:`calib.estimator.solver.linearise` (None: by problem size).
    """
    from .problem import make_layout  # (problem ↔ observability: layout after each fix)

    _check_counts(p)
    found = {}
    fixed = {k: v.copy() for k, v in p.fixed_cols.items()}
    for _ in range(4 * p.N * 8):  # each pass fixes at least one column
        p = p.replace(fixed_cols={k: v.copy() for k, v in fixed.items()})
        lay = make_layout(p)
        cols, untouched = _null_direction(p, lay, kinds, st, rel_tol, dense)
        if cols is None:
            break
        support = _support_blocks(p, lay, cols)
        if not support or (untouched and len(support) < len(cols)):
            raise ObservabilityError(f"the data cannot determine {_what(p, lay, cols, st)}")
        for i, key, label, k in support:
            found[(i, label)] = True
        # untouched columns all at once, else the array column the null direction moves most
        for i, key, _, k in (support if untouched else support[:1]):
            mask = fixed.setdefault(key, np.zeros(getattr(lay, key).shape, bool))
            mask[(i, k) if mask.ndim == 2 else i] = True
    else:
        raise ObservabilityError("the data leave too many parameters undetermined")
    return p.replace(unobservable=[
        {"parameter": label, "array": str(p.names[i]),
         "reason": "the data do not determine it (rank-deficient Fisher information: too few measurements of "
                   "this array); not estimated (kept at its initial value, NaN std), the other parameters are"}
        for (i, label) in sorted(found)])


def _null_direction(p, lay, kinds, st, rel_tol, dense):
    """The weakest direction of Jn if it is (numerically) null: ({column: |weight|}, untouched), else
    (None, False). Untouched columns (zero norm) come first, all at once (``untouched`` True)."""
    J = linearise(p, st, lay, kinds, dense=dense).J
    sparse = scipy.sparse.issparse(J)
    norms = np.sqrt(np.asarray(J.multiply(J).sum(axis=0)).ravel()) if sparse else np.linalg.norm(J, axis=0)
    if np.any(norms == 0):
        return {int(k): 1.0 for k in np.flatnonzero(norms == 0)}, True
    if sparse:
        s_min, s_max, v = _weakest_direction_sparse(J, lay)
    else:  # eigen-decomposition of the small n × n matrix JnᵀJn: σ² = its eigenvalues (resolves σ ≥ 1e-7)
        Jn = J / norms
        G = Jn.T @ Jn
        lam = np.linalg.eigvalsh(G)   # (values only: ~2.5x cheaper than with the vectors)
        if not _is_null(np.sqrt(max(lam[0], 0.0)) / _VALUES_MARGIN, np.sqrt(lam[-1]), rel_tol, J.shape[1]):
            return None, False   # far from the limit: the eigenvectors' decomposition would decide the same
        lam, V = np.linalg.eigh(G)
        s_min, s_max, v = np.sqrt(max(lam[0], 0.0)), np.sqrt(lam[-1]), V[:, 0]
    if _is_null(s_min, s_max, rel_tol, J.shape[1]):
        v = np.abs(v)
        keep = np.flatnonzero(v >= NULL_SUPPORT * v.max())
        return {int(k): float(v[k]) for k in keep}, False
    return None, False


# The values-only decomposition decides "not null" only when the smallest singular value is this many
# times above the limit (its eigenvalues may differ from eigh's in the last bits); closer, eigh decides.
_VALUES_MARGIN = 10.0


def _is_null(s_min, s_max, rel_tol, n):
    """Whether the smallest singular value ``s_min`` of an (·, n) column-normalised Jacobian is null."""
    return s_min < rel_tol * s_max * np.sqrt(n) or s_min < ABS_SINGULAR


def _support_blocks(p, lay, cols):
    """Non-reference array parameters among ``cols`` ({column: weight}), largest weight first:
    (array, layout key, label, component)."""
    out = []
    for a in (a for a in ARRAY_PARAMS if a.can_freeze):
        idx = getattr(lay, a.key).reshape(p.N, -1)
        for i, k in np.argwhere(idx >= 0):
            c = int(idx[i, k])
            if c in cols and (i != p.ref or a.reference == "free"):
                out.append((cols[c], int(i), a.key, a.label, int(k)))
    return [b[1:] for b in sorted(out, key=lambda b: -b[0])]


def _what(p, lay, cols, st):
    """Words for the parameters of a null direction no array parameter can absorb."""
    worst = sorted(cols, key=lambda k: -cols[k])[:3]
    what = ", ".join(dict.fromkeys(describe_param(p, lay, k) for k in worst))
    s = st.s - st.s.mean(0)
    sv = np.linalg.svd(s, compute_uv=False)
    return what + (" (all sources are nearly collinear)" if sv[1] < 1e-3 * max(sv[0], 1e-12) else "")


def _check_counts(p):
    """The spread of the source path (cheap, named error). Arrays without DOAs for 2 events keep their
    orientation out of the estimate (``build_problem``); arrays without TDOA-M leave their offset to the
    rank check (undetermined, the rest calibrated)."""
    K = p.K
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
    for a in ARRAY_PARAMS:
        hit = np.argwhere(getattr(lay, a.key).reshape(p.N, -1) == k)
        if hit.size:
            return f"the {a.label} of array {p.names[hit[0, 0]]}"
    hit = np.argwhere(lay.s == k)
    if hit.size:
        return f"the position of source (event {p.events[hit[0, 0]]})"
    hit = np.argwhere(lay.e == k)
    if hit.size:
        return f"the emission time of event {p.events[hit[0, 0]]}"
    return f"parameter {k}"
