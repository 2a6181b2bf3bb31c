"""Per-array arrival sigmas (meta ``sigma_arrival_per_array``, issue 27): boards of different makes time their
arrivals unequally well; the frontend states each array's arrival sigma and the estimator weights its TDOA
rows by it, relative to the type's sigma."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.errors import InputError
from calib.estimator import calibrate
from calib.estimator.factors import evaluate
from calib.estimator.problem import arrival_scales, build_problem, make_layout, retract, state_from_dict
from calib.frontend.extract import noise_estimates
from calib.pipeline.formats.io import validate_meta
from calib.pipeline.simulate.featsim import simulate_features

SIGMA = 1e-5      # s, TDOA rows of the clean arrays
NOISY = 6.0       # the noisy array's arrivals: this × the others'


def test_scales_are_relative_to_the_pool_and_few_mic_boards_never_below_it():
    names = ["A", "B", "C", "D"]
    six = [[0.0, 0.0, 0.0]] * 6
    meta = {"sigma_arrival_per_array": {"A": 1e-6, "B": 1e-6, "C": 4e-6, "D": 1e-6},
            "mics": {"A": six, "B": six, "C": six, "D": [[0.0, 0.0, 0.0]] * 2}}
    rows = np.array([0, 0, 1, 1, 2, 2, 3, 3])                 # two TDOA-S rows per array
    pool2 = (1 + 1 + 16 + 1) / 4 * 1e-12
    own2 = np.array([1e-12, 1e-12, 16e-12, 1e-12]) / pool2
    # the 6-mic boards as claimed, either way; the 2-mic pair (D) claims less than the pool: held at the pool
    want = np.sqrt([own2[0], own2[1], own2[2], 1.0])
    np.testing.assert_allclose(arrival_scales(meta, names, rows), want)
    np.testing.assert_allclose(arrival_scales({}, names, rows), 1.0)
    # an array without a value gets the pool's
    np.testing.assert_allclose(arrival_scales({"sigma_arrival_per_array": {"C": 4e-6}}, names, rows), 1.0)
    # without mics in meta every board counts as few: low claims held at the pool
    np.testing.assert_allclose(arrival_scales({**meta, "mics": {}}, names, rows),
                               np.sqrt([1.0, 1.0, own2[2], 1.0]))


CIRCLE = [[0.0463 * np.cos(k * np.pi / 3), 0.0463 * np.sin(k * np.pi / 3), 0.0] for k in range(6)]


def _stated(feats, own):
    """``feats`` with each array's arrival sigma ``own`` stated, every array a 6-mic circle (claims taken either
    way; problem.FEW_MICS)."""
    return {**feats, "meta": {**feats["meta"], "sigma_arrival_per_array": own,
                              "mics": {n: CIRCLE for n in feats["meta"]["arrays"]}}}


def test_rows_are_weighted_by_their_arrays_sigma_and_the_jacobian_stays_exact():
    feats, _ = simulate_features(3, SIGMA, seed=1)
    names = feats["meta"]["arrays"]
    rng = np.random.default_rng(0)
    own = {n: float(v) for n, v in zip(names, rng.uniform(0.5e-6, 5e-6, len(names)))}
    p, plain = build_problem(_stated(feats, own)), build_problem(feats)
    a = p.arrival_scale
    np.testing.assert_allclose(p.tdoa_s.scale, a[p.tdoa_s.arr])
    np.testing.assert_allclose(p.tdoa_m.scale, np.sqrt((a[p.tdoa_m.arr] ** 2 + a[p.ref] ** 2) / 2))
    st = state_from_dict({"x": rng.normal(0, 2, (p.N, 3)), "R": Rotation.random(p.N, random_state=1).as_matrix(),
                          "offset": rng.normal(0, 1e-3, p.N), "drift": rng.normal(0, 1e-5, p.N),
                          "s": rng.normal(0, 2, (p.K, 3)), "e": np.zeros(p.K), "odo_yaw": np.zeros(1)})
    lay = make_layout(p)
    for f, g, rows in zip(evaluate(p, st, lay, ["tdoa_s", "tdoa_m"]), evaluate(plain, st, lay, ["tdoa_s", "tdoa_m"]),
                          (p.tdoa_s, p.tdoa_m)):
        np.testing.assert_allclose(f.r * rows.scale, g.r, rtol=1e-12)
        np.testing.assert_allclose(f.sigma_rows, g.sigma * rows.scale)
        assert g.sigma_rows is None          # without the key: one sigma per kind, as before
        J = np.asarray(f.J)
        num = np.zeros_like(J)
        for k in range(lay.n):
            h = np.zeros(lay.n)
            h[k] = 1e-6
            rp = evaluate(p, retract(st, lay, h), lay, [f.kind])[0].r
            rm = evaluate(p, retract(st, lay, -h), lay, [f.kind])[0].r
            num[:, k] = (rp - rm) / 2e-6
        np.testing.assert_allclose(J, num, atol=1e-4 * np.abs(num).max())


def test_the_frontend_states_each_arrays_rms_of_its_clean_arrivals():
    def result(sd, flags):
        return {"arrival_sd": np.array(sd), "spread": np.array(sd), "doa_spread": np.full(len(sd), 0.01),
                "flags": flags}
    res = {"A": result([1e-6, 3e-6, 50e-6], [(), (), ("nlos",)]),     # the flagged arrival does not count
           "B": result([2e-6, 2e-6], [(), ("doa_spread",)]),          # a DOA-only doubt does not concern timing
           "C": result([np.nan, 0.0], [(), ()])}                      # nothing to estimate from: left out
    est = noise_estimates(res)
    np.testing.assert_allclose(est["sigma_arrival_per_array"]["A"], np.sqrt((1 + 9) / 2) * 1e-6)
    np.testing.assert_allclose(est["sigma_arrival_per_array"]["B"], 2e-6)
    assert "C" not in est["sigma_arrival_per_array"]
    np.testing.assert_allclose(est["sigma_tdoa"], np.sqrt(2) * np.sqrt((1 + 9 + 4 + 4) / 4) * 1e-6)


def test_meta_key_is_checked():
    meta = {"speed_of_sound": 343.0, "reference_array": "A", "arrays": ["A", "B"]}
    assert validate_meta({**meta, "sigma_arrival_per_array": {"A": 1e-6}})["sigma_arrival_per_array"] == {"A": 1e-6}
    for bad in ({"Z": 1e-6}, {"A": -1.0}, {"A": "1e-6"}, [1e-6]):
        with pytest.raises(InputError, match="sigma_arrival_per_array"):
            validate_meta({**meta, "sigma_arrival_per_array": bad})


def _noisier(feats, bad, rng):
    """Features with array ``bad``'s arrivals NOISY × the others' (featsim's rows are independent: TDOA-S rows
    get NOISY² − 1 more variance, TDOA-M rows (NOISY² + 1) / 2 − 1)."""
    out = dict(feats)
    for kind, extra in (("tdoa_s", NOISY ** 2 - 1), ("tdoa_m", (NOISY ** 2 + 1) / 2 - 1)):
        df = feats[kind].copy()
        m = (df["array"] == bad).to_numpy()
        df.loc[m, "tdoa"] = df.loc[m, "tdoa"] + rng.normal(0.0, SIGMA * np.sqrt(extra), m.sum())
        out[kind] = df
    return out


@pytest.mark.slow
def test_a_noisier_board_stated_keeps_honest_error_bars_and_does_not_pull_the_others():
    """One array's arrivals 6x the others' (a 2-mic pair among circles). Stated per array (meta's sigma_tdoa
    the pooled one, as the frontend writes it), that array is kept with error / std of a Gaussian's size and
    the other arrays' errors are no larger than with the pooled sigma for every row."""
    z_bad, others_with, others_without = [], [], []
    for seed in range(12):
        feats, truth = simulate_features(3, SIGMA, 5.0, 0.03, seed=3000 + seed)
        names = feats["meta"]["arrays"]
        bad = names[1 + seed % (len(names) - 1)]
        f = _noisier(feats, bad, np.random.default_rng(seed))
        own = {n: SIGMA / np.sqrt(2) * (NOISY if n == bad else 1.0) for n in names}
        n_rows = f["tdoa_s"]["array"].value_counts()
        pooled = np.sqrt(2 * np.average([own[n] ** 2 for n in n_rows.index], weights=n_rows.to_numpy()))
        f = {**f, "meta": {**f["meta"], "sigma_tdoa": float(pooled)}}
        t = truth["arrays"].set_index("array")
        for stated, others in ((True, others_with), (False, others_without)):
            a = calibrate(_stated(f, own) if stated else f, noise="estimate")["arrays"].set_index("array")
            err = np.linalg.norm(a[["x", "y", "z"]].to_numpy(float) - t.loc[a.index, ["x", "y", "z"]].to_numpy(float),
                                 axis=1)
            i = list(a.index).index(bad)
            others.append(np.delete(err, [0, i]))
            if stated:
                std = np.linalg.norm(a.loc[bad, ["x_std", "y_std", "z_std"]].to_numpy(float))
                assert np.isfinite(std), f"seed {seed}: the stated noisy array was dropped"
                z_bad.append(err[i] / std)
    z_bad = np.array(z_bad)
    assert np.sqrt(np.mean(z_bad ** 2)) < 1.6 and z_bad.max() < 3.0, z_bad
    rms = [np.sqrt(np.mean(np.concatenate(o) ** 2)) for o in (others_with, others_without)]
    assert rms[0] <= 1.05 * rms[1], rms
