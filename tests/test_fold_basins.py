"""A planar board whose sources all lie near its mic plane has two fold basins (issue 27, ``init.fold_basins``).

Folded DOAs tell only each source's |elevation| above the board's mic plane; with every source within 20° of
it, the tilt that turns the sources' mean elevation e into −e fits too. Scenes of the feature-level simulator
against their ground truth: a planar board (A4) 5 m beside a lawn-mower path whose sources lie 2–11° above its
mic plane, DOA noise 5° (the two basins' separation δ² 0.5–12: often not decided) or 1° (δ² 50–4000).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.estimator import calibrate
from calib.geometry import fold
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features

POSITIONS = [[0, 0, 0], [5.0, 0.5, 0.2], [0.5, 4.5, 0.3], [3.0, -5.0, -0.2]]   # A4: the planar board
FOLD_REASON = "where planar DOAs fold"


def _scene(seed, sigma_doa_deg, k=12, height_spread=0.6, tilt_deg=4.0):
    """Features with A4's DOAs folded across a mic plane tilted ``tilt_deg`` from level, away from the path (its
    sources then lie about 2–7° above that plane; the path's height varies by ``height_spread``). Returns
    (features, truth, elevations of A4's true directions above its mic plane (deg))."""
    rng = np.random.default_rng(1000 + seed)
    t = np.linspace(0.0, 1.0, k)
    stops = np.column_stack([0.5 + 5.0 * np.abs(((3 * t) % 2) - 1), 0.3 + 4.5 * t,
                             -0.4 + height_spread * rng.uniform(0.0, 1.0, k)])
    feats, truth = simulate_features(stops, 5e-6, sigma_doa_deg, 0.005, seed=seed, positions=POSITIONS)
    q = truth["arrays"].set_index("array").loc["A4", ["qx", "qy", "qz", "qw"]].to_numpy(float)
    towards = (stops - POSITIONS[3]).mean(axis=0) * [1.0, 1.0, 0.0]
    axis = np.cross([0.0, 0.0, 1.0], towards / np.linalg.norm(towards))
    normal_w = Rotation.from_rotvec(np.radians(tilt_deg) * axis).apply([0.0, 0.0, 1.0])
    normal = Rotation.from_quat(q).inv().apply(normal_w)   # A4's frame
    d = feats["doa"].copy()
    m = (d.array == "A4").to_numpy()
    src = truth["sources"].set_index("event").loc[d.loc[m, "event"], ["x", "y", "z"]].to_numpy(float)
    w = src - POSITIONS[3]
    elev = np.degrees(np.arcsin(w @ normal_w / np.linalg.norm(w, axis=1)))
    u = d[["ux", "uy", "uz"]].to_numpy().copy()
    u[m] = fold(u[m], normal)
    d[["ux", "uy", "uz"]] = u
    meta = {**feats["meta"], "doa_mirror_normals": {"A4": normal.tolist()}}
    return feats.replace(doa=d, meta=meta), truth, elev


def _a4(cal, truth):
    """A4's (orientation error (deg), the norm of its orientation stds (deg), named for its fold)."""
    err = {r["array"]: r for r in evaluate(cal, truth)["per_array"]}["A4"]["geodesic_deg"]
    std = float(np.degrees(np.linalg.norm(cal["arrays"].set_index("array").loc["A4", ["rx_std", "ry_std", "rz_std"]])))
    named = any(r.startswith("array A4:") and FOLD_REASON in r for r in cal["report"]["verdict"]["reasons"])
    return err, std, named


def test_the_scene_puts_every_source_near_the_mic_plane():
    _, _, elev = _scene(0, 5.0)
    assert 0.0 < elev.min() and elev.max() < 12.0


def test_a_lower_basin_within_the_noise_is_named_when_taken():
    """Seed 3 (σ_DOA 5°): the other basin, 9° away, fits 1.0 better (δ² 6.5: not decided). The lower cost is
    reported; it must be named and its std must cover the other basin (the truth). Before, a basin lower by
    more than 1 replaced the solution silently: A4 9.9° off, std 5.1°, named only as imprecise."""
    feats, truth, _ = _scene(3, 5.0)
    cal = calibrate(feats)
    rec = [r for r in cal["report"]["stages"]["fold_basins"] if r["array"] == "A4" and r["ambiguous"]]
    assert rec and rec[0]["switched"] and rec[0]["separation_chi2"] < 36.0
    err, std, named = _a4(cal, truth)
    assert named and err < 2.0 * std, (err, std)


@pytest.mark.slow
@pytest.mark.parametrize("sigma_doa_deg", [5.0, 1.0])
def test_the_cost_alone_decides_fold_basins_safely(sigma_doa_deg):
    """Over 8 draws: the two basins' Δχ² (the reported one's minus the other's) follows its linear-Gaussian law
    δ² ± 2δ (δ² ``separation_chi2``), so a choice on ½ Δχ² ≥ 4.5 alone is 3σ-safe even where δ² is below
    the mirror check's 36 (unlike a mirror solution across coplanar sources, where costs differed by up to 9
    with δ² 2.5–17): every basin the cost decided is the true one, every undecided one is named, and A4 is never
    more than 3σ off unnamed (measured: (Δχ² − δ²)/2δ std 0.89, |max| 3.0 over 169 basin pairs with δ² < 100)."""
    small = 0
    for seed in range(8):
        feats, truth, _ = _scene(seed, sigma_doa_deg)
        cal = calibrate(feats)
        err, std, named = _a4(cal, truth)
        assert err < 3.0 * std or named, (seed, err, std)
        for r in cal["report"]["stages"].get("fold_basins", []):
            if r["rotation_deg"] < 2.0:
                continue     # slid back into the solution's basin
            assert r["ambiguous"] == (abs(r["dcost"]) < 4.5) and (named or not r["ambiguous"]), (seed, r)
            if not r["ambiguous"]:
                assert err < 0.5 * r["rotation_deg"] or err < 2.0 * std, (seed, err, r)   # the true basin reported
                small += r["separation_chi2"] < 36.0
            d = np.sqrt(r["separation_chi2"])
            dchi2 = 2.0 * (-r["dcost"] if r["switched"] else r["dcost"])
            if err < 0.5 * r["rotation_deg"] and d < 10.0:   # (far apart, the first-order δ² is rougher)
                assert abs(dchi2 - d * d) < 3.5 * 2.0 * d + 1.0, (seed, r)
    if sigma_doa_deg == 5.0:
        assert small >= 2   # the scene has decisions the separation rule would have refused


@pytest.mark.parametrize("seed", [8, 35])
def test_a_tilt_that_makes_the_sources_straddle_the_plane_is_named(seed):
    """A flat path (heights within 0.2 m), σ_DOA 5°: in 2 of 40 draws (these seeds) the solve lands 13–16° off,
    tilted about the sources' mean direction so that they straddle the mic plane (estimated elevations −7…+5°
    for true 2–4°), with a std of 4.2° (3.2–3.8σ). A tilt across that direction by ∓2e (e ≈ 0 there) does not
    reach the true basin; the orientations with every source on one side of the plane do (``fold_candidates``):
    it fits within 1.0–1.5, so A4 is named for its fold and its std covers the error."""
    feats, truth, _ = _scene(seed, 5.0, height_spread=0.2)
    cal = calibrate(feats)
    err, std, named = _a4(cal, truth)
    assert named and err < 2.0 * std, (err, std)
