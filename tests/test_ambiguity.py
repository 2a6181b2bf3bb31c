"""An array pose with a second solution must never look settled (issue 27, ``estimator.ambiguity``).

Sources in one plane (a robot's speaker at a constant height) leave every array's mirror image across that
plane the same ranges; a linear board's cone angles and a planar board's folded DOAs do not break the tie, a
3-D board's DOAs do. Scenes of the feature-level simulator against their ground truth: coplanar sources (the
mirror must be named and covered by the std), sources whose height varies (nothing named, every array placed),
and a solve started at the mirror (it must be taken back).
"""
from __future__ import annotations

import numpy as np
import pytest

from calib.estimator import calibrate
from calib.estimator.ambiguity import mirror_pose
from calib.estimator.calibrate import calibrate_features
from calib.estimator.problem import build_problem
from calib.estimator.uncertainty import state_from_frames
from calib.frontend.doa import cone_vectors
from calib.geometry import fold
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features

AXIS = np.array([1.0, 0.0, 0.0])     # A2: a linear board along its x axis
NORMAL = np.array([0.0, 0.0, 1.0])   # A3: a planar board, mic plane normal along its z axis
POSITIONS = [[0, 0, 0], [4.0, 0.5, -0.2], [0.5, 4.0, 0.3], [4.0, 4.0, 0.1]]


def _stops(height_variation, k=24, seed=0):
    """A lawn-mower path over 4 × 4 m, 1 m below the reference array, its height varying by ± this much."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, k)
    x = 4.0 * np.abs(((3 * t) % 2) - 1)
    y = 4.0 * t
    z = -1.0 + height_variation * np.sin(2 * np.pi * 2.5 * t) + 0.002 * rng.standard_normal(k) * (height_variation > 0)
    return np.column_stack([x, y, z])


def _scene(height_variation, seed=1):
    """Features of A1 (reference) and A4 (3-D DOAs), A2 (linear: cone angles) and A3 (planar: folded DOAs)."""
    feats, truth = simulate_features(_stops(height_variation), 5e-6, 1.0, 0.005, seed=seed, positions=POSITIONS)
    d = feats["doa"].copy()
    u = d[["ux", "uy", "uz"]].to_numpy().copy()
    a2, a3 = (d.array == "A2").to_numpy(), (d.array == "A3").to_numpy()
    u[a2] = cone_vectors(AXIS, u[a2] @ AXIS)
    u[a3] = fold(u[a3], NORMAL)
    d[["ux", "uy", "uz"]] = u
    meta = {**feats["meta"], "doa_axes": {"A2": AXIS.tolist()}, "doa_mirror_normals": {"A3": NORMAL.tolist()}}
    return feats.replace(doa=d, meta=meta), truth


def _errors(cal, truth):
    """{array: (position error (m), the norm of its position stds (m))}."""
    per = {r["array"]: r for r in evaluate(cal, truth)["per_array"]}
    arr = cal["arrays"].set_index("array")
    return {a: (per[a]["position_m"], float(np.linalg.norm(arr.loc[a, ["x_std", "y_std", "z_std"]].to_numpy(float))))
            for a in ("A2", "A3", "A4")}


def test_the_mirror_pose_fits_a_linear_and_a_planar_board_exactly():
    """With the sources in a plane, the mirrored pose (x' across the plane, R' = M R D) predicts the same
    ranges, cone angles and folded DOAs as the true pose (hand geometry, no solver)."""
    feats, truth = _scene(0.0)
    p = build_problem(feats)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    for i, check in ((1, "cone"), (2, "fold")):
        x2, R2, plane = mirror_pose(p, st, i)
        assert plane["source_spread_m"] < 1e-9
        np.testing.assert_allclose(np.linalg.det(R2), 1.0, atol=1e-12)
        r1, r2 = (np.linalg.norm(st.s - x, axis=1) for x in (st.x[i], x2))
        np.testing.assert_allclose(r1, r2, atol=1e-9)
        u1 = (st.s - st.x[i]) @ st.R[i] / r1[:, None]
        u2 = (st.s - x2) @ R2 / r2[:, None]
        if check == "cone":
            np.testing.assert_allclose(u1 @ AXIS, u2 @ AXIS, atol=1e-9)
        else:
            np.testing.assert_allclose(fold(u1, NORMAL), fold(u2, NORMAL), atol=1e-9)
            assert np.max(np.abs(u1 - u2)) > 0.1    # (unfolded, they differ)


def test_coplanar_sources_name_the_mirror_and_the_std_covers_it():
    """Coplanar sources: A2 (linear) and A3 (planar) each have a mirror solution ~0.4-2.6 m away that fits as
    well; both are named, and whichever solution was reported the truth is within 2 of its stated stds. The
    3-D board A4 is not named for it."""
    feats, truth = _scene(0.0)
    cal = calibrate(feats)
    rec = {r["array"]: r for r in cal["report"]["stages"]["mirror_basins"]}
    assert set(rec) == {"A2", "A3"}
    assert all(r["ambiguous"] for r in rec.values())
    mirror_reasons = [t for t in cal["report"]["verdict"]["reasons"] if "mirror solution" in t]
    assert {a for a in ("A2", "A3", "A4") if any(f"array {a}:" in t for t in mirror_reasons)} == {"A2", "A3"}
    assert {"A2", "A3"} <= set(cal["report"]["verdict"]["flagged_arrays"])
    assert cal["report"]["verdict"]["status"] != "ok"
    for a, (err, std) in _errors(cal, truth).items():
        assert err < 2.0 * std, (a, err, std)
    # calibration.json's covariance covers the mirror as the std columns do
    labels, C = cal["array_covariance"]
    k = [labels.index(f"A2.{c}") for c in "xyz"]
    d = np.asarray(rec["A2"]["displacement_m"])
    assert d @ np.linalg.solve(C[np.ix_(k, k)], d) <= 1.0 + 1e-9


def test_height_variation_breaks_the_tie():
    """Sources whose height varies by ± 0.4 m: the mirrors are tried and clearly excluded; nothing is named
    for them and every array is placed within its stated error (the scene's noise: ~1 cm)."""
    feats, truth = _scene(0.4)
    cal = calibrate(feats)
    rec = cal["report"]["stages"].get("mirror_basins", [])
    assert {r["array"] for r in rec} <= {"A2", "A3"}
    assert not any(r["ambiguous"] or r["switched"] for r in rec)
    assert not any("mirror solution" in t for t in cal["report"]["verdict"]["reasons"])
    for a, (err, std) in _errors(cal, truth).items():
        assert err < min(3.0 * std, 0.1), (a, err, std)


@pytest.mark.parametrize("name, height", [("A2", 0.05), pytest.param("A3", 0.05, marks=pytest.mark.slow), ("A2", 0.1)])
def test_a_solve_started_at_the_mirror_is_taken_back(name, height):
    """The solve started with one board at its mirror image (a wrong basin: the data, with their height
    variation, prefer the truth): either the joint solve keeps it there and the mirror check takes the better
    solution, or the joint solve drops it as inconsistent and its mirror rejoins it; every array ends within
    its stated error, none dropped. (Without the check: A2 1.1-1.4 m off, std 2.5 cm.)"""
    feats, truth = _scene(height)
    p = build_problem(feats)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    i = list(p.names).index(name)
    st.x[i], st.R[i], _ = mirror_pose(p, st, i)
    cal = calibrate_features(feats, init_state=st)
    stages = cal["report"]["stages"]
    switched = {r["array"] for r in stages.get("mirror_basins", []) if r["switched"]}
    rejoined = {r["array"] for r in stages.get("mirror_rejoined", []) if r["rejoined"]}
    assert name in switched | rejoined
    assert not cal["report"]["unreliable_arrays"]
    err = _errors(cal, truth)
    assert all(e < min(3.0 * s, 0.1) for e, s in err.values()), err


def test_a_set_up_mirror_finding_the_data_decided_becomes_a_note():
    """The set-up check names an array's possible mirror from the odometry's shape alone; where the estimate
    refitted that mirror and the data decided (clearly worse, or better and taken) it is a note, where they did
    not (ambiguous) it stays ``suspect``; other findings are left alone."""
    from calib.pipeline.setupcheck import settled_by_estimate

    def finding(a, check="trajectory"):
        return {"status": "suspect", "what": "events.csv", "check": check, "text": f"{a} may be mirrored", "array": a}

    def tried(a, dcost, switched=False, ambiguous=False):
        return {"array": a, "dcost": dcost, "position_m": 1.5, "switched": switched, "ambiguous": ambiguous}

    report = {"stages": {"mirror_basins": [tried("A2", 24.0), tried("A3", -6.0, switched=True),
                                           tried("A4", 0.3, ambiguous=True)]}}
    found = settled_by_estimate([finding("A2"), finding("A3"), finding("A4"), finding("A5"),
                                 finding("A2", check="geometry scale")], report)
    assert [f["status"] for f in found] == ["note", "note", "suspect", "suspect", "suspect"]
    assert "excluded: it fits worse by 24.0" in found[0]["text"] and "taken" in found[1]["text"]
    assert settled_by_estimate([finding("A2")], {}) == [finding("A2")]


def test_a_level_planar_board_below_a_level_path_is_named():
    """A planar board with its mic plane horizontal, 25 cm below a path at constant height (a table mount; the
    set-up check exempts horizontal source planes): its mirror is the same orientation 50 cm higher (M R D = R),
    so neither its TDOAs nor its folded DOAs (nor the fold basins, which slide into that mirror) tell the two
    apart: it is named, and its stated position std covers the other solution."""
    from scipy.spatial.transform import Rotation

    positions = [[0, 0, 0], [5.5, 2.0, -1.25], [0.5, 4.0, 0.3], [4.0, 4.0, 0.1]]
    feats, truth = simulate_features(_stops(0.0), 5e-6, 1.0, 0.005, seed=3, positions=positions)
    q = truth["arrays"].set_index("array").loc["A2", ["qx", "qy", "qz", "qw"]].to_numpy(float)
    normal = Rotation.from_quat(q).inv().apply([0.0, 0.0, 1.0])   # A2's frame: its mic plane is horizontal
    d = feats["doa"].copy()
    u = d[["ux", "uy", "uz"]].to_numpy().copy()
    a2 = (d.array == "A2").to_numpy()
    u[a2] = fold(u[a2], normal)
    d[["ux", "uy", "uz"]] = u
    feats = feats.replace(doa=d, meta={**feats["meta"], "doa_mirror_normals": {"A2": normal.tolist()}})
    cal = calibrate(feats)
    rec = {r["array"]: r for r in cal["report"]["stages"]["mirror_basins"]}
    assert rec["A2"]["ambiguous"] and rec["A2"]["position_m"] == pytest.approx(0.5, abs=0.05)
    assert any(t.startswith("array A2: its pose has a mirror solution") for t in cal["report"]["verdict"]["reasons"])
    err, std = _errors(cal, truth)["A2"]
    assert std > 0.45 and err < 2.0 * std
