"""Array geometries beyond full 3-D DOAs: linear arrays and 2-mic pairs (cone measurements).

A linear array measures only the angle θ between its axis ``a`` (array frame) and the source direction
(``factors.cone``). Its position and clock come from the TDOAs; the axis direction in the world,
``b = R a``, from ``b · n_j = cos θ_j`` over the sources; the roll about the axis is not observable and
not estimated (its rotation component is fixed in the layout, its std reported NaN).

Without a full DOA the initialisation places such an array (and a single microphone) by its TDOAs alone,
where sources close to a plane leave a second minimum near the mirror image of the array across that
plane; :func:`reseat` compares the two by a local fit of the array alone.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib.geometry import mirror

from .init import MIN_CONE_ROWS, subproblem
from .problem import make_layout
from .solver import levenberg_marquardt


def axis_from_cones(n, cos_theta):
    """Unit axis b (3,) with b·n_k ≈ cos θ_k for unit directions n (m, 3), or None if undetermined."""
    if len(n) < MIN_CONE_ROWS:
        return None
    b, *_ = np.linalg.lstsq(n, cos_theta, rcond=None)
    norm = np.linalg.norm(b)
    return b / norm if norm > 1e-9 else None


def init_cone_axes(p, st):
    """Rotate each cone array so its axis points along the world axis its cone rows imply (in place);
    then every array without full DOAs is :func:`reseat`-ed."""
    for i in np.flatnonzero(p.rot_fixed_axis >= 0):
        if i == p.ref:
            continue
        st = _align_axis(p, st, i)
    for i in np.flatnonzero((p.rot_fixed_axis >= 0) | ~p.rot_free):
        if i != p.ref:
            st = reseat(p, st, i)
    return st


# an array without full DOAs: its own TDOA and cone rows (sources fixed) decide between starts
RESEAT_KINDS = ("tdoa_s", "tdoa_m", "cone")
RESEAT_ITER = 30


def reseat(p, st, i):
    """Array i (no full DOA) at the better of its current place and its mirror image across the sources'
    best-fit plane: each start refined by a robust fit of the array alone (position, axis, clock; sources
    and other arrays fixed), the lower cost kept. Returns the state (a copy when it changed)."""
    s = st.s - st.s.mean(axis=0)
    n = np.linalg.svd(s, full_matrices=False)[2][-1]
    q = subproblem(p, [i])   # its own TDOA rows (other arrays' rows do not move with it)
    lay = make_layout(q, arrays=[i], sources=False, ref_drift=False, odo_yaw=False)
    kinds = list(RESEAT_KINDS)
    best, best_cost = st, None
    for x0 in (st.x[i], mirror(st.x[i], n, origin=st.s.mean(axis=0))):
        trial = st.copy()
        trial.x[i] = x0
        if p.rot_fixed_axis[i] >= 0:
            trial = _align_axis(p, trial, i)
        trial, info = levenberg_marquardt(q, trial, lay, kinds, loss="cauchy", k=3.0, max_iter=RESEAT_ITER)
        if best_cost is None or info["cost"] < best_cost:
            best, best_cost = trial, info["cost"]
    return best


def _align_axis(p, st, i):
    """Array i's rotation turned so its axis points along the world axis its cone rows imply."""
    m = p.cone.arr == i
    w = st.s[p.cone.ev[m]] - st.x[i]
    b = axis_from_cones(w / np.linalg.norm(w, axis=1, keepdims=True), p.cone.cos[m])
    if b is not None:
        rot, _ = Rotation.align_vectors(b[None], p.cone_axis[i][None])
        st.R[i] = rot.as_matrix()
    return st
