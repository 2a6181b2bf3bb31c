"""Per-array variance components (issue 10, item 2): against simulated ground truth and finite differences."""
import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.estimator import calibrate
from calib.estimator.arraynoise import ARRAY_MAX_FACTOR, update_scales
from calib.estimator.factors import evaluate
from calib.estimator.problem import build_problem, make_layout, retract, state_from_dict
from calib.pipeline.simulate.featsim import simulate_features

_spec = importlib.util.spec_from_file_location("bench_faults", Path(__file__).parents[1] / "benchmarks" / "bench_faults.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def _noisy_doas(feats, array, factor, rng):
    """The DOAs of ``array`` with ``factor`` × the scene's noise (extra rotations of the featsim model)."""
    doa = feats["doa"].copy()
    m = (doa.array == array).to_numpy()
    axis = rng.normal(size=(m.sum(), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.deg2rad(rng.normal(0.0, np.sqrt(factor ** 2 - 1) * bench.SIGMA_DOA_DEG, (m.sum(), 1)))
    doa.loc[m, ["ux", "uy", "uz"]] = Rotation.from_rotvec(axis * ang).apply(doa.loc[m, ["ux", "uy", "uz"]].to_numpy(float).copy())
    return {**feats, "doa": doa}


def test_per_array_scaling_keeps_the_jacobian_exact():
    feats, _ = simulate_features(3, seed=1)
    p = build_problem(feats)
    rng = np.random.default_rng(0)
    p = p.replace(array_scale={k: rng.uniform(1.0, 3.0, p.N) for k in ("tdoa_s", "tdoa_m", "doa")})
    st = state_from_dict({"x": rng.normal(0, 2, (p.N, 3)), "R": Rotation.random(p.N, random_state=1).as_matrix(),
                          "offset": rng.normal(0, 1e-3, p.N), "drift": np.zeros(p.N), "s": rng.normal(0, 2, (p.K, 3)),
                          "e": np.zeros(p.K), "odo_yaw": np.zeros(1)})
    lay = make_layout(p)
    kinds = ["tdoa_s", "tdoa_m", "doa"]
    fs = evaluate(p, st, lay, kinds)
    plain = evaluate(p.replace(array_scale={}), st, lay, kinds)
    for f, g in zip(fs, plain):
        arr = np.repeat(p.rows(f.kind).arr, f.dim)
        np.testing.assert_allclose(f.r * p.array_scale[f.kind][arr], g.r)
        np.testing.assert_allclose(f.sigma_rows, g.sigma * p.array_scale[f.kind][arr])
        J = np.asarray(f.J)
        num = np.zeros_like(J)
        for k in range(lay.n):
            h = np.zeros(lay.n)
            h[k] = 1e-6
            rp = [x.r for x in evaluate(p, retract(st, lay, h), lay, [f.kind])][0]
            rm = [x.r for x in evaluate(p, retract(st, lay, -h), lay, [f.kind])][0]
            num[:, k] = (rp - rm) / 2e-6
        np.testing.assert_allclose(J, num, atol=1e-4 * np.abs(num).max())


def test_array_components_are_bounded():
    p = SimpleNamespace(array_scale={"doa": np.ones(3)}, array_own={"doa": np.array([True, True, False])})
    groups = {"ss": np.array([1e4, 1.0, 1e4]), "red": np.array([10.0, 10.0, 10.0])}
    update_scales(p, "doa", groups, type_step=1.0, total=1.0, bound=100.0)
    # own and far noisier: at ARRAY_MAX_FACTOR; own and quieter than its type: not below it; not own: unchanged
    np.testing.assert_allclose(p.array_scale["doa"], [ARRAY_MAX_FACTOR, 1.0, 1.0])
    p.array_scale["doa"] = np.ones(3)
    update_scales(p, "doa", groups, type_step=1.0, total=2.5, bound=3.0)   # a stated prior: 3x in total
    assert p.array_scale["doa"][0] * 2.5 <= 3.0 + 1e-12


def test_clean_scenes_get_no_array_component():
    """Same noise on every array: no array gets its own sigma, the solution is the per-type one."""
    for seed in range(3):
        feats, _ = simulate_features(1 + seed, 1e-4, 5.0, 0.03, seed=1000 + seed)
        a = calibrate(feats, noise="estimate")
        b = calibrate(feats, noise="estimate", array_noise=True)
        assert not any(b["report"]["sigmas"]["per_array_factor"].values())
        np.testing.assert_allclose(b["arrays"][["x", "y", "z"]].to_numpy(float),
                                   a["arrays"][["x", "y", "z"]].to_numpy(float), atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_much_noisier_array_gets_its_own_sigma(seed):
    """One array with 5x the DOA noise: unless the array test already dropped it, that array (only) gets a
    DOA factor above 1.5 (the outlier tests trim its tails first: about 2 for a true 5), at most the bound. (At 3x the tests
    find it in only part of the runs with 14 events: CHANGELOG.md.)"""
    feats, truth = simulate_features(3, 1e-4, 5.0, 0.03, seed=2000 + seed)
    bad = feats["meta"]["arrays"][1 + seed]
    f2 = _noisy_doas(feats, bad, 5.0, np.random.default_rng(seed))
    rep = calibrate(f2, noise="estimate", array_noise=True)["report"]
    fac = rep["sigmas"]["per_array_factor"]
    if bad not in rep["unreliable_arrays"]:
        assert 1.5 < fac["doa"].get(bad, 0.0) <= ARRAY_MAX_FACTOR
    assert all(set(d) <= {bad} for d in fac.values())


def test_array_noise_option_is_validated():
    from calib.estimator import validate_options
    with pytest.raises(ValueError, match="array_noise"):
        validate_options(array_noise="yes")


def test_arrival_variances_combine_the_prior_gate_normalise_and_clip():
    """Hand values of arraynoise.arrival_variances: an array moves from its prior only with enough redundancy;
    the mean over the TDOA-S rows is held at 1 or above (the frontend's figure redistributed, not lowered)."""
    from calib.estimator.arraynoise import ARRAY_MIN_REDUNDANCY, ARRIVAL_MAX_FACTOR, ARRIVAL_PRIOR_DOF, arrival_variances

    P = ARRIVAL_PRIOR_DOF
    v = np.array([0.25, 0.25, 9.0, 4.0])
    red = np.array([20.0, 20.0, 20.0, ARRAY_MIN_REDUNDANCY - 1])   # the last: too little to move it
    prior = np.ones(4)
    rows = np.repeat(np.arange(4), 5)
    raw = np.array([(0.25 * 20 + P) / (20 + P)] * 2 + [(9 * 20 + P) / (20 + P), 1.0])
    np.testing.assert_allclose(arrival_variances(v, red, prior, rows), raw / min(raw.mean(), 1.0))
    # every array quieter than stated: normalised up to a mean of 1 (their ratios kept)
    quiet = arrival_variances(np.array([0.1, 0.4]), np.array([50.0, 50.0]), np.ones(2), np.array([0, 1]))
    np.testing.assert_allclose(quiet.mean(), 1.0)
    np.testing.assert_allclose(quiet[1] / quiet[0], (0.4 * 50 + P) / (0.1 * 50 + P))
    # clipped to the allowed factor either way
    big = arrival_variances(np.array([1e4, 1.0]), np.array([1e3, 1e3]), np.ones(2), np.array([0, 1]))
    assert big[0] == ARRIVAL_MAX_FACTOR ** 2


def _arrival_noise(feats, sig, rng):
    """``feats`` (exact TDOAs) whose TDOA rows are differences of one error per (array, event), array a's with std
    ``sig[a]``, as a frontend's are; meta says so, and its sigma_tdoa is the frontend-style pooled figure."""
    names, ref = feats["meta"]["arrays"], feats["meta"]["reference_array"]
    n = {(a, int(e)): rng.normal(0.0, sig[a]) for a in names for e in feats["events"]["event"]}
    tm, ts = feats["tdoa_m"].copy(), feats["tdoa_s"].copy()
    tm["tdoa"] += [n[(a, int(e))] - n[(ref, int(e))] for a, e in zip(tm["array"], tm["event"])]
    ts["tdoa"] += [n[(a, int(b))] - n[(a, int(c))] for a, c, b in zip(ts["array"], ts["from_event"], ts["to_event"])]
    pooled = np.sqrt(2 * np.mean([sig[a] ** 2 for a in names]))
    meta = {**feats["meta"], "sigma_tdoa": float(pooled), "sigmas_estimated": ["sigma_tdoa"],
            "tdoa_shared_arrivals": True}
    return feats.replace(tdoa_m=tm, tdoa_s=ts, meta=meta)


def test_residuals_find_the_array_whose_arrivals_are_noisier():
    """Six arrays, 40 stops, one array's arrivals 3x the others' and no per-array claim: where the redundancy
    allows, the arrays' arrival components (variance.estimate_arrival_scales) give that array the largest
    scale, well above the others' (with one session-wide sigma every array's would be 1)."""
    for seed in range(4):
        rng = np.random.default_rng(900 + seed)
        stops = np.column_stack([rng.uniform(0, 6, 40), rng.uniform(0, 5, 40), rng.uniform(0.5, 2.0, 40)])
        feats, _ = simulate_features(stops, 1e-9, 2.0, 0.03, seed=900 + seed, n_arrays=6)
        names = feats["meta"]["arrays"]
        bad = 1 + seed % 5
        f = _arrival_noise(feats, {a: 3e-6 if k == bad else 1e-6 for k, a in enumerate(names)},
                           np.random.default_rng(seed))
        a = calibrate(f, noise="estimate").problem.arrival_scale
        others = np.delete(a, [0, bad])          # (the reference's own has little redundancy here)
        assert np.argmax(a) == bad and a[bad] > 1.4 * np.median(others), (seed, a)
