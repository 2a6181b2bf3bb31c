"""Measured data are immutable: a Problem's arrays and mappings cannot be written in place, and every
estimator stage leaves the problem it was given exactly as it was (hash of every array and setting)."""
import dataclasses
import hashlib

import numpy as np
import pytest

from calib.estimator import arraynoise, calibrate
from calib.estimator.factors import active_kinds
from calib.estimator.init import subproblem
from calib.estimator.joint import joint_solve, solve_from
from calib.estimator.motion import corrected
from calib.estimator.observability import check_observability
from calib.estimator.problem import Problem, build_problem, make_layout
from calib.estimator.staging import initial_state
from calib.estimator.variance import estimate_noise, reweighted, robust_noise_steps
from calib.pipeline.simulate.featsim import simulate_features


def fingerprint(obj, h=None):
    """SHA-256 over every array (dtype, shape, bytes), mapping, sequence and scalar reachable from ``obj``."""
    top = h is None
    h = hashlib.sha256() if top else h
    if isinstance(obj, np.ndarray):
        h.update(f"{obj.dtype}{obj.shape}".encode())
        h.update(obj.tobytes() if obj.dtype != object else repr(obj.tolist()).encode())
    elif dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            h.update(f.name.encode())
            fingerprint(getattr(obj, f.name), h)
    elif hasattr(obj, "items"):
        for k, v in obj.items():
            h.update(repr(k).encode())
            fingerprint(v, h)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            fingerprint(v, h)
    else:
        h.update(repr(obj).encode())
    return h.hexdigest() if top else None


@pytest.fixture(scope="module")
def scene():
    """A scene that exercises every setting: odometry in a rotated frame (the yaw test), one array without
    TDOA-S and with one TDOA-M (its offset and drift undetermined), noise re-estimated per array."""
    f, _ = simulate_features(3, seed=4)
    ev = f["events"].copy()
    c, s = np.cos(0.4), np.sin(0.4)
    x, y = ev["odom_x"].to_numpy(), ev["odom_y"].to_numpy()
    ev["odom_x"], ev["odom_y"] = c * x - s * y, s * x + c * y
    tm, ts, a3 = f["tdoa_m"], f["tdoa_s"], f["meta"]["arrays"][3]
    return {**f, "events": ev, "tdoa_m": tm[(tm["array"] != a3) | (tm["event"] == tm["event"].min())],
            "tdoa_s": ts[ts["array"] != a3]}


def test_measurements_cannot_be_written_in_place(scene):
    p = build_problem(scene, odometry_yaw=True)
    for a in (p.odom, p.t, p.events, p.fold, p.rot_free, p.doa.u, p.doa.scale, p.tdoa_m.val, p.tdoa_s.a, p.cone.cos):
        with pytest.raises(ValueError, match="read-only"):
            a[...] = 0
    with pytest.raises(ValueError, match="read-only"):
        p.tdoa_m.val += 1e-3
    with pytest.raises(TypeError):
        p.sigma["doa"] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.odo_yaw_free = False
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.doa.u = np.zeros((0, 3))
    q = arraynoise.start_scales(p, active_kinds(p))
    with pytest.raises(ValueError, match="read-only"):
        q.array_scale["doa"][0] = 2.0
    # a copy with changes is a new problem; the original keeps its values
    r = p.replace(sigma={**p.sigma, "doa": 1.0})
    assert r.sigma["doa"] == 1.0 and p.sigma["doa"] != 1.0
    # the caller's own array is not frozen by being put into a problem
    odom = np.zeros((p.K, 3))
    p.replace(odom=odom)
    odom[0, 0] = 1.0


def _unchanged(p, stage):
    before = fingerprint(p)
    out = stage(p)
    assert fingerprint(p) == before
    return out


def test_every_stage_leaves_its_problem_unchanged(scene):
    p = build_problem(scene, odometry_yaw=True)
    kinds = active_kinds(p)
    opts = {"loss": "cauchy", "robust_k": 3.0, "max_iter": 50}
    p1, st, _, _ = _unchanged(p, lambda q: initial_state(q, kinds, method="hybrid", times={}, **opts))
    assert p1.unobservable and p1.fixed_cols and p1.odo_yaw_test is not None   # the stage changed settings ...
    assert not p.unobservable and not p.fixed_cols and p.odo_yaw_test is None  # ... in a new problem only
    _unchanged(p, lambda q: check_observability(q, make_layout(q), kinds, st))
    p2 = _unchanged(p1, lambda q: arraynoise.start_scales(q, kinds))
    res = _unchanged(p2, lambda q: joint_solve(q, st, kinds, {}, scene["meta"], noise="estimate", loss="cauchy",
                                               robust_k=3.0, outlier_threshold=5.0, max_iter=50))
    _unchanged(p2, lambda q: solve_from(q, st, kinds=kinds, loss=None, max_iter=50))
    _unchanged(res.problem, lambda q: estimate_noise(q, res.state, kinds, res.mask, max_iter=50))
    stated = {k: p1.sigma[k] for k in reweighted()}
    _unchanged(p1, lambda q: robust_noise_steps(q, st, make_layout(q), kinds, bounds={k: 100.0 for k in stated},
                                                stated=stated, **opts))
    _unchanged(p1, lambda q: corrected(q, st, np.ones((q.K, 3))))
    _unchanged(p1, lambda q: subproblem(q, np.arange(q.N), doa_arrays=[q.ref]))
    p0 = build_problem(scene, odometry_yaw=True)
    _unchanged(p0, lambda q: calibrate(scene, problem=q))


def test_problem_fields_are_all_frozen():
    """Every field of a Problem is an immutable value (read-only array, read-only mapping, tuple, scalar)."""
    f, _ = simulate_features(1, seed=0)
    p = build_problem(f)
    for fld in dataclasses.fields(Problem):
        v = getattr(p, fld.name)
        if isinstance(v, np.ndarray):
            assert not v.flags.writeable, fld.name
        elif isinstance(v, (dict, list)):
            pytest.fail(f"{fld.name} is a mutable {type(v).__name__}")


def test_problems_and_results_pickle_and_stay_frozen():
    """Programs send problems and calibrate()'s results between processes (Monte-Carlo, Dask)."""
    import pickle

    f, _ = simulate_features(1, seed=0)
    p = build_problem(f)
    q = pickle.loads(pickle.dumps(p))
    assert fingerprint(q) == fingerprint(p)
    with pytest.raises(ValueError, match="read-only"):
        q.doa.u[0, 0] = 0.0
    with pytest.raises(TypeError):
        q.sigma["doa"] = 1.0
    res = pickle.loads(pickle.dumps(calibrate(f)))
    assert fingerprint(res["problem"]) == fingerprint(calibrate(f)["problem"])
