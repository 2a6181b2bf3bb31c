"""The odometry frame: its rotation about the vertical relative to the reference array's frame.

Convention (docs/method.md, "Odometry frame"): the odometry's z axis is the reference array's z axis;
the odometry's x-y axes are rotated by the yaw ψ about it, so a step measured as Δo in the odometry frame
is ``Rz(ψ) Δo`` in the reference frame (``factors.odometry_frame``). ψ is estimated with the rest when the
odometry moves horizontally (``problem.odometry_yaw_observable``); its start value comes from the
reference array's DOAs here, by a grid over ψ of the angular misfit of the source chain on their rays
(mirror-ambiguous DOAs of a planar reference array unfolded on the way).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib.geometry import mirror, yaw_rotate

from .uncertainty import param_std


COARSE_STEP_DEG = 5.0   # grid over the full circle, then refined
FINE_STEP_DEG = 0.25


def rotate_odometry(odom, yaw):
    """Cumulative odometry (K, 3) expressed in the reference frame for the odometry yaw ``yaw`` (rad)."""
    return Rotation.from_euler("z", yaw).apply(np.array(odom, float))


UNFOLD_PASSES = 3   # mirror-ambiguous reference DOAs: alternations of (chain fit, side choice per DOA)


def ray_misfit(p, yaws):
    """Σ (1 − cos angle) between the reference DOAs and the source chain fitted to them, per yaw (Y,) → (Y,).

    The chain's start point is the linear least-squares point of ``init.init_sources`` (the DOAs' lines vs.
    ``s_0 + Rz(ψ) o_j``). Full DOAs: its normal matrix does not depend on ψ, so all yaws are solved at
    once. A line fit cannot tell a chain in front of the array from one behind it: ψ + 180° with
    ``−s_0`` is the same set of lines, up to the odometry's vertical part (Rz leaves z alone), so a
    misfit of lines (sin²) has a twin minimum there: exact for a robot on a flat floor (it won 6 of 12 such
    sessions), near for bench_clocks' walks up and down 1.4 m (7 of 400). The misfit is the rays'
    (1 − cos: a source behind its DOA costs 2 per event), which the twin cannot fake.

    Mirror-ambiguous reference DOAs (planar reference array, fold normal n): each DOA is used on the side of
    the mic plane where the chain fitted so far lies, alternating with the chain fit (``UNFOLD_PASSES``),
    still for all yaws at once.
    """
    m = p.doa.arr == p.ref
    u, j = p.doa.u[m], p.doa.ev[m]
    n = p.fold[p.ref]
    o = (p.odom - p.odom[0])[j]                                   # (n, 3)
    oy = yaw_rotate(o, np.atleast_1d(yaws))                       # (Y, n, 3) = Rz(ψ) o
    U = np.broadcast_to(u, oy.shape)
    for _ in range(UNFOLD_PASSES if np.any(n) else 1):
        P = np.eye(3) - U[..., :, None] * U[..., None, :]                # (Y, n, 3, 3)
        A = P.sum(1)
        if np.any(np.linalg.cond(A) > 1e8):
            return np.full(len(yaws), np.inf)
        s0 = -np.linalg.solve(A, np.einsum("ynab,ynb->ya", P, oy)[..., None])[..., 0]   # (Y, 3)
        v = s0[:, None, :] + oy
        v /= np.maximum(np.linalg.norm(v, axis=2, keepdims=True), 1e-12)
        if np.any(n):
            U = np.where(((v @ n) * (U @ n) < 0)[..., None], mirror(U, n), U)
    return np.sum(1.0 - np.einsum("yna,yna->yn", v, U), axis=1)


def initial_yaw(p):
    """Start value of the odometry yaw (rad) from the reference array's DOAs (mirror-ambiguous ones
    unfolded by :func:`ray_misfit`); 0 when they cannot tell (fewer than 3)."""
    m = p.doa.arr == p.ref
    if m.sum() < 3:
        return 0.0
    coarse = np.deg2rad(np.arange(-180.0, 180.0, COARSE_STEP_DEG))
    best = coarse[int(np.argmin(ray_misfit(p, coarse)))]
    fine = best + np.deg2rad(np.arange(-COARSE_STEP_DEG, COARSE_STEP_DEG + 1e-9, FINE_STEP_DEG))
    y = float(fine[int(np.argmin(ray_misfit(p, fine)))])
    return float(np.angle(np.exp(1j * y)))


# The yaw is kept free only when the data say the frames differ: |ψ| above this many σ. Below it the
# odometry frame is taken as the reference frame (ψ = 0), as before this parameter existed: on the eight
# real sets ψ comes out at −4..−6° (1.8° σ), a bias of the reference array's own DOAs that a free yaw
# would pass on to every array position (mean location error 7.1 → 10.3 cm).
YAW_SIGNIFICANCE = 5.0


def yaw_is_significant(yaw, yaw_std, level=YAW_SIGNIFICANCE):
    """True when the estimated yaw differs from 0 by more than ``level`` standard deviations."""
    return bool(yaw_std is not None and np.isfinite(yaw_std) and abs(yaw) > level * yaw_std)


def yaw_decision(p, st, Jw, k):
    """Test the odometry yaw (column k of the whitened Jacobian Jw, state ``st``). Returns (problem, state,
    {yaw_deg, std_deg, kept}); when the yaw is not significant it is fixed: a new problem with
    ``odo_yaw_free`` False and a new state with ``odo_yaw`` 0 (the inputs are not changed)."""
    yaw, sd = float(np.angle(np.exp(1j * st.odo_yaw[0]))), param_std(Jw, k)   # yaw in (−π, π]: 360° is no yaw
    test = {"yaw_deg": float(np.rad2deg(yaw)), "std_deg": float(np.rad2deg(sd)), "kept": yaw_is_significant(yaw, sd)}
    if not test["kept"]:
        p = p.replace(odo_yaw_free=False)
        st = st.copy()
        st.odo_yaw = np.zeros(1)
    return p, st, test
