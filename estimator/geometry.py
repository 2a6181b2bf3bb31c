"""Array geometries beyond full 3-D DOAs: linear arrays and 2-mic pairs (cone measurements).

A linear array measures only the angle θ between its axis ``a`` (array frame) and the source direction
(``factors.cone``). Its position and clock come from the TDOAs; the axis direction in the world,
``b = R a``, from ``b · n_j = cos θ_j`` over the sources; the roll about the axis is not observable and
not estimated (its rotation component is fixed in the layout, its std reported NaN).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

MIN_CONE_ROWS = 3   # a world axis from fewer cone rows is left where it is


def axis_from_cones(n, cos_theta):
    """Unit axis b (3,) with b·n_k ≈ cos θ_k for unit directions n (m, 3), or None if undetermined."""
    if len(n) < MIN_CONE_ROWS:
        return None
    b, *_ = np.linalg.lstsq(n, cos_theta, rcond=None)
    norm = np.linalg.norm(b)
    return b / norm if norm > 1e-9 else None


def init_cone_axes(p, st):
    """Rotate each cone array so its axis points along the world axis its cone rows imply (in place)."""
    for i in np.flatnonzero(p.rot_fixed_axis >= 0):
        if i == p.ref:
            continue
        m = p.cone.arr == i
        w = st.s[p.cone.ev[m]] - st.x[i]
        b = axis_from_cones(w / np.linalg.norm(w, axis=1, keepdims=True), p.cone.cos[m])
        if b is None:
            continue
        a = p.cone_axis[i]
        rot, _ = Rotation.align_vectors(b[None], a[None])
        st.R[i] = rot.as_matrix()
    return st
