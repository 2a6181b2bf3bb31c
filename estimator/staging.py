"""The stages before the joint solve: initialisation (hybrid or Wang et al.'s, by name in
:data:`INIT_METHODS`), the observability check, and the paper's stage 1, the IVE.

:func:`initial_state` returns the problem those stages leave (undetermined parameters left out, the
odometry yaw kept free or fixed) with the start state; the problem it was given is not changed.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from calib.geometry import mirror

from .factors import active_kinds
from .geometry import init_cone_axes
from .init import doa_rotation, initialise, kabsch, subproblem
from .observability import check_observability
from .odoframe import initial_yaw, rotate_odometry, yaw_decision
from .problem import Problem, State, make_layout
from .solver import levenberg_marquardt, linearise
from .uncertainty import whiten


def _wang_initialise(p):
    from .wang import wang_initialise  # (wang builds on this module's solver: imported when chosen)

    return wang_initialise(p)


# Initialisation methods by name (``calibrate(method=...)``): a new method is one entry here.
INIT_METHODS = {"hybrid": initialise, "wang": _wang_initialise}


class Start(NamedTuple):
    """:func:`initial_state`'s outcome: the problem the stages leave (undetermined parameters out, the
    odometry yaw's freedom decided), the start state of the joint solve, the stages' records for report.json
    ``stages`` ({"init", "ive"}: cost, iterations, ...) and the state after each stage."""
    problem: Problem
    state: State
    stages: dict
    stage_states: dict


def initial_state(p, kinds, *, method, loss, robust_k, max_iter, times):
    """Initialisation (hybrid or Wang et al.'s) in the odometry frame's start yaw, the observability check,
    then the IVE (hybrid with TDOA-S), where the odometry yaw is kept or fixed. Returns a :class:`Start`
    (the given problem is not changed); ``times`` gets "init", "observability" and "ive" (s).
    """
    t0 = time.perf_counter()
    stages, stage_states = {}, {}
    # the odometry frame's yaw: a start value from the reference DOAs, the initialisation in that frame
    yaw0 = initial_yaw(p) if p.odo_yaw_free else 0.0
    p_init = p.replace(odom=rotate_odometry(p.odom, yaw0), odo_yaw_free=False)
    st, init_info = INIT_METHODS[method](p_init)
    st.odo_yaw = np.array([yaw0])
    st = init_cone_axes(p, st)
    times["init"] = time.perf_counter() - t0
    lay_full = make_layout(p)
    t_obs = time.perf_counter()
    p = check_observability(p, lay_full, kinds, st)
    times["observability"] = time.perf_counter() - t_obs
    stages["init"] = {"cost": float(linearise(p, st, lay_full, kinds).cost), **_jsonable(init_info)}
    stage_states["init"] = st.copy()
    if method == "hybrid" and len(p.tdoa_s.val) > 0:
        t1 = time.perf_counter()
        p, st, stages["ive"] = ive(p, st, loss=loss, robust_k=robust_k, max_iter=max_iter)
        stage_states["ive"] = st.copy()
        times["ive"] = time.perf_counter() - t1
    return Start(p, st, stages, stage_states)


def ive(p, st, *, loss, robust_k, max_iter):
    """Stage 1 (IVE): positions, clocks and sources from hybrid TDOA, odometry and the reference array's
    DOAs; then rotations by SVD alignment of DOA-scaled points. The odometry yaw is decided here (its σ
    from the IVE's data is a conservative one), so the joint pass starts in the right parameter set.
    Returns (problem with the yaw decision, state, stage record)."""
    q = subproblem(p, np.arange(p.N), doa_arrays=[p.ref])
    lay_ive = make_layout(q, rotations=False)
    kinds_ive = active_kinds(q, "ive")
    st, info = levenberg_marquardt(q, st, lay_ive, kinds_ive, loss=loss, k=robust_k, max_iter=max_iter, rtol=1e-6)
    st = init_cone_axes(p, rotations_by_kabsch(p, st))
    if lay_ive.odo_yaw[0] >= 0:
        lin = linearise(q, st, lay_ive, kinds_ive, loss=loss, k=robust_k)
        p, st, test = yaw_decision(p, st, whiten(lin.J, lin.w), int(lay_ive.odo_yaw[0]))
        p = p.replace(odo_yaw_test=test)
    return p, st, {"cost": info["cost"], "iterations": info["iterations"], "reason": info["reason"]}


def rotations_by_kabsch(p, st):
    """Each non-reference array's rotation by SVD alignment of DOA-scaled points (the paper's IVE step);
    ``st.R`` is updated in place."""
    for i in range(p.N):
        m = p.doa.arr == i
        if i == p.ref or m.sum() < 2:
            continue
        j = p.doa.ev[m]
        w = st.s[j] - st.x[i]
        d = np.linalg.norm(w, axis=1, keepdims=True)
        u = p.doa.u[m]
        n = p.fold[i]
        if np.any(n):
            # mirror-ambiguous DOAs: decide which events lie behind the mic plane afresh from the IVE's
            # positions and sources, which no longer depend on this array's DOAs
            u = np.where(((w @ doa_rotation(p, st, i, st.x[i])) @ n < 0)[:, None], mirror(u, n), u)
        st.R[i], _ = kabsch(u * d, w)
    return st


def _jsonable(d):
    return {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in d.items()
            if isinstance(v, (int, float, str, np.floating, dict))}
