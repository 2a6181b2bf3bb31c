"""Second solutions of an array's pose: the mirror image across the sources' plane (issue 27).

When the sources an array hears lie near one plane (a robot's speaker at a near-constant height), the array's
position reflected across that plane, x' = x − 2 ((x − c)·m) m, has the same range to every source, so
the same TDOAs: |s − x'|² = |s − x|² + 4 d h with d, h the array's and the source's distances from the plane.
Only the sources' height variation h tells the two apart through the arrivals. The DOAs break the tie only
for a board that measures a 3-D direction: the mirrored directions need the improper rotation M R. A board
that does not (``mirror_free``) fits the mirror exactly with a proper rotation M R D, D a reflection in the
array's own frame that its DOAs cannot see:

- a linear board or a pair measures a cone angle about its axis a: D across a plane that holds a;
- a planar board without a stated hemisphere measures its DOAs folded across its mic plane (normal n):
  D = I − 2 n nᵀ;
- an array without DOA rows (a single mic, or too few DOAs to estimate its orientation): any D.

:func:`mirror_basins` refits each such array at its mirror image, first alone (the other arrays and the
sources held), then jointly with everything from there, and compares the joint costs (½ χ² with the
session's sigmas, the joint solve's rows) and how far apart the two solutions' predictions are (:func:`separation`): the lower cost is reported; when the data do not decide (costs within
``MIRROR_DCOST``, or solutions less than ``SEPARATION_MIN`` apart) the verdict names the array and its std
covers the other solution (``uncertainty.cover_alternative``).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation

from calib.geometry import mirror

from .problem import make_layout
from .solver import levenberg_marquardt, linearise

MIRROR_DCOST = 4.5    # ½ Δχ²: a mirror within this cost (3σ, one parameter's worth) is not excluded by the data ...
SEPARATION_MIN = 36.0  # ... nor one whose separation δ² (χ², :func:`separation`) is below this: the observed Δχ²
#                        is ±δ² ± 2δ, so a choice is 3σ-safe from δ/2 = 3 on (exactly symmetric scenes: δ² 2.5-17)
MIRROR_MIN_M = 0.05   # a mirror closer than this to the solution is the same basin (an array near the plane)
ALONE_ITER = 40       # iterations of the alone-fit (ten parameters at most)
RESTART_KAPPA = 3.0   # a fresh placement's robust clock scale, in the array's arrival σ (the robust passes' k)


def mirror_free(p, i):
    """Whether array ``i``'s DOAs leave its mirror image across a plane of sources a proper rotation:
    a planar board with folded DOAs, a linear board or a pair, or an array whose orientation is not
    estimated (no DOAs used)."""
    return bool(np.any(p.fold[i]) or p.rot_fixed_axis[i] >= 0 or not p.rot_free[i])


def board_kind(p, i):
    """"planar" (folded DOAs), "linear" (a cone about an axis) or "none" (no DOAs used) for a mirror-free array."""
    return "planar" if np.any(p.fold[i]) else "linear" if p.rot_fixed_axis[i] >= 0 else "none"


def other_rotvec(p, i, Ra, Rb):
    """The rotation (rotation vector, rad, array ``i``'s own axes) from orientation ``Ra`` to ``Rb`` that the data
    see: a linear board's turn of its axis alone (its roll about the axis is not determined), else the whole."""
    if p.rot_fixed_axis[i] < 0:
        return Rotation.from_matrix(Ra.T @ Rb).as_rotvec()
    a = np.asarray(p.cone_axis[i], float)
    b = Ra.T @ Rb @ a
    k = np.cross(a, b)
    s = np.linalg.norm(k)
    return np.zeros(3) if s < 1e-12 else k / s * np.arctan2(s, a @ b)


def heard_events(p, i):
    """Indices of the events array ``i`` has any row of (TDOA, DOA, cone)."""
    ev = [p.tdoa_m.ev[p.tdoa_m.arr == i], p.tdoa_s.a[p.tdoa_s.arr == i], p.tdoa_s.b[p.tdoa_s.arr == i],
          p.doa.ev[p.doa.arr == i], p.cone.ev[p.cone.arr == i]]
    return np.unique(np.concatenate(ev)).astype(int)


def source_plane(s):
    """(centroid (3,), unit normal (3,), RMS distance from the plane (m)) of the points ``s`` (n, 3)."""
    c = s.mean(axis=0)
    _, sv, vt = np.linalg.svd(s - c, full_matrices=False)
    return c, vt[-1], float(sv[-1] / np.sqrt(len(s)))


def frame_reflection(p, i, R, m):
    """The reflection D (3 × 3, array frame) that array ``i``'s DOAs cannot see, chosen so that M R D (M the
    world reflection across the plane with normal ``m``) is the mirror's proper rotation: across the mic plane
    of a planar board, across a plane holding a linear board's axis (the one that turns m's image least)."""
    if np.any(p.fold[i]):
        n = np.asarray(p.fold[i], float)
    else:
        a = np.asarray(p.cone_axis[i], float) if p.rot_fixed_axis[i] >= 0 else np.zeros(3)
        v = R.T @ m
        n = v - (v @ a) * a
        if np.linalg.norm(n) < 1e-6:   # m along the axis: any plane holding it
            n = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    n = n / np.linalg.norm(n)
    return np.eye(3) - 2.0 * np.outer(n, n)


def mirror_pose(p, st, i):
    """Array ``i``'s pose mirrored across the best-fit plane of the sources it hears: (x', R', plane
    record) or None with fewer than 3 such sources."""
    ev = heard_events(p, i)
    if len(ev) < 3:
        return None
    c, m, rms = source_plane(st.s[ev])
    M = np.eye(3) - 2.0 * np.outer(m, m)
    x = mirror(st.x[i], m, origin=c)
    R = M @ st.R[i] @ frame_reflection(p, i, st.R[i], m)
    return x, R, {"normal": m.tolist(), "source_spread_m": rms, "array_distance_m": float(abs((st.x[i] - c) @ m))}


def mirror_basins(p, st, lay, kinds, mask, *, skip=(), max_iter=200):
    """Each mirror-free array's (:func:`mirror_free`) mirror image across its sources' plane, refitted: alone
    (its pose and clock; the others and the sources held), then jointly (every parameter of ``lay``, least
    squares on the rows of ``mask``). The data decide between the two when the joint costs differ by
    MIRROR_DCOST and the solutions are :func:`separation` SEPARATION_MIN apart; either way the lower cost is
    taken. Returns (state, records): one record per array tried {array, board, dcost_alone, dcost (joint),
    separation_chi2, position_m, plane, ambiguous (not decided), switched (the mirror taken), rotation_deg,
    rotvec (3,: rad, the reported solution's array frame to the other one's; a linear board's axis turn),
    displacement_m (3,: the other solution's position minus the reported one's)}. ``skip``: array indices
    not tried (refitted alone, dropped)."""
    cost0 = linearise(p, st, lay, kinds, mask=mask).cost
    records = []
    for i in range(p.N):
        if i == p.ref or i in skip or not mirror_free(p, i):
            continue
        rec = _try_mirror(p, st, lay, kinds, mask, i, cost0, max_iter)
        if rec is None:
            continue
        alt = rec.pop("state")
        records.append(rec)
        if rec["switched"]:
            st, cost0 = alt, cost0 + rec["dcost"]
    return st, records


def _try_mirror(p, st, lay, kinds, mask, i, cost0, max_iter):
    """One array's mirror refitted (:func:`mirror_basins`): its record with the refitted ``state``, or None."""
    pose = mirror_pose(p, st, i)
    if pose is None or np.linalg.norm(pose[0] - st.x[i]) < MIRROR_MIN_M:
        return None
    alt = st.copy()
    alt.x[i], alt.R[i], plane = pose
    alone = make_layout(p, arrays=[i], sources=False, ref_drift=False, emission=False, odo_yaw=False)
    alt, _ = levenberg_marquardt(p, alt, alone, kinds, mask=mask, max_iter=ALONE_ITER)
    d_alone = float(linearise(p, alt, lay, kinds, mask=mask).cost - cost0)
    # jointly: an array in the wrong basin pulls the sources toward it (alone +111, jointly −66 in a test scene)
    alt, _ = levenberg_marquardt(p, alt, lay, kinds, mask=mask, max_iter=max_iter)
    dcost = float(linearise(p, alt, lay, kinds, mask=mask).cost - cost0)
    rec = {"array": str(p.names[i]), "board": board_kind(p, i), "dcost_alone": d_alone, "dcost": dcost,
           "separation_chi2": separation(p, st, alt, lay, kinds, mask),
           "position_m": float(np.linalg.norm(alt.x[i] - st.x[i])), "plane": plane}
    apart = rec["position_m"] >= MIRROR_MIN_M   # the refit may have slid back into the solution's basin
    rec["ambiguous"] = bool(apart and (abs(dcost) < MIRROR_DCOST or rec["separation_chi2"] < SEPARATION_MIN))
    # the lower cost is reported: clearly (decided) or not (ambiguous: then named, and its std covers the other)
    rec["switched"] = bool(apart and dcost < (0.0 if rec["ambiguous"] else -MIRROR_DCOST))
    here, other = (alt, st) if rec["switched"] else (st, alt)
    phi = other_rotvec(p, i, here.R[i], other.R[i])   # from the reported solution to the other one
    rec.update(rotation_deg=float(np.degrees(np.linalg.norm(phi))), rotvec=phi.tolist(),
               displacement_m=(other.x[i] - here.x[i]).tolist(), state=alt)
    return rec


def separation(p, st0, alt, lay, kinds, mask):
    """δ² (χ² units): how far the predictions of the solution ``alt`` lie from those of ``st0`` beyond what the
    parameters of ``lay`` can absorb near ``alt`` — the noise-free Δχ² that would separate the two solutions
    (to first order: the whitened prediction difference e = r(alt) − r(st0) off the column space of J(alt),
    ‖(I − P) e‖²). Under either solution as the truth the observed Δχ² is ±δ² with a std of 2δ, so the data
    tell the two apart only when δ is several times 2; the observed Δχ² alone does not say so (coplanar
    sources, exactly symmetric: the two minima's costs still differed by up to 9)."""
    l0 = linearise(p, st0, lay, kinds, mask=mask)
    l1 = linearise(p, alt, lay, kinds, mask=mask)
    keep = l1.w > 0
    e = (l1.r - l0.r)[keep]
    J = l1.J[keep]
    if scipy.sparse.issparse(J):
        d = scipy.sparse.linalg.lsqr(J, e, atol=1e-10, btol=1e-10, iter_lim=10 * J.shape[1])[0]
    else:
        d = np.linalg.lstsq(J, e, rcond=None)[0]
    return float(np.sum((e - J @ d) ** 2))


def retry_dropped(p, res, kinds, joint):
    """Arrays the joint solve dropped as inconsistent (``res.dropped`` with an ``inconsistent`` record) that
    may have been solved in a wrong basin: their refit alone starts where the joint solve left them, so it
    stays there. Each one's other starts — a mirror-free array's mirror image across the sources' plane, and
    fresh placements (``init.restart_poses``: the grid search's minima, a linear board's or a pair's cone rows
    included, with the others' sources, which are better than the reference array's alone) — refitted alone
    on its own rows (robust; the others and the sources held); when the best fits clearly better (by
    MIRROR_DCOST), the joint solve is run again from there (``joint(p, state) -> JointResult``) and kept if it
    no longer drops the array and drops no other (office: a pair's four arrivals 0.4-0.8 ms late put its start
    55 cm off in height; solved there it was dropped and refitted alone 66 cm off). Returns (the result,
    records {array, dcost_alone, position_m, start: "mirror" or "placed", rejoined})."""
    q = res.problem   # (the session's sigmas; ``p``, as stated, starts the joint solve again)
    inconsistent = {a["array"] for a in res.arrays if a.get("inconsistent")}
    records = []
    for i in list(res.dropped):
        if str(p.names[i]) not in inconsistent:
            continue
        alone = make_layout(q, arrays=[i], sources=False, ref_drift=False, emission=False, odo_yaw=False)
        here = linearise(q, res.state, alone, kinds, loss="cauchy").cost
        fits = []
        for start, alt in _restarts(q, res.state, i):
            alt, info = levenberg_marquardt(q, alt, alone, kinds, loss="cauchy", max_iter=ALONE_ITER)
            fits.append((float(info["cost"] - here), start, alt))
        if not fits:
            continue
        dcost, start, alt = min(fits, key=lambda f: f[0])
        rec = {"array": str(p.names[i]), "dcost_alone": dcost, "start": start,
               "position_m": float(np.linalg.norm(alt.x[i] - res.state.x[i])), "rejoined": False}
        records.append(rec)
        if rec["dcost_alone"] >= -MIRROR_DCOST or rec["position_m"] < MIRROR_MIN_M:
            continue
        new = joint(p, alt)
        if i not in new.dropped and set(new.dropped) <= set(res.dropped):
            res, rec["rejoined"] = new, True
    return res, records


def _restarts(q, st, i):
    """[(kind, state)]: array ``i``'s other starts for :func:`retry_dropped`."""
    from .init import restart_poses   # (init imports this module's separation)

    out = []
    pose = mirror_pose(q, st, i) if mirror_free(q, i) else None
    if pose is not None:
        alt = st.copy()
        alt.x[i], alt.R[i], _ = pose
        out.append(("mirror", alt))
    scale = 1.0 if q.arrival_scale is None else float(q.arrival_scale[i])
    kappa = RESTART_KAPPA * float(q.sigma["tdoa_m"]) * scale
    sigma_d = float(q.sigma["cone"] if q.rot_fixed_axis[i] >= 0 else q.sigma["doa"])
    return out + [("placed", alt) for alt in restart_poses(q, st, i, kappa, sigma_d)]
