"""The sparse estimator (Schur complement, block covariance, sparse observability) against the dense one.

The dense path (``dense=True``: dense Jacobian, Cholesky of the whole normal matrix, pinv covariance, dense
eigen-decomposition for observability) is the independent reference: on problems small enough for both, the sparse path
must give the same minimum (cost within 1e-9 relative, parameters within 1e-6 of their σ), the same
covariance blocks, the same observability verdicts, and exact draws from the CRLB.
"""
import numpy as np
import pytest
import scipy.sparse
from scipy.spatial.transform import Rotation

from calib.estimator import ObservabilityError
from calib.estimator.factors import FACTORS
from calib.estimator.observability import check_observability
from calib.estimator.problem import build_problem, make_layout
from calib.estimator.solver import levenberg_marquardt, linearise
from calib.estimator.uncertainty import cov_block, covariance, state_from_frames, std_from_cov
from calib.pipeline.simulate.featsim import simulate_features

KINDS = ["tdoa_s", "tdoa_m", "doa", "odometry"]


def perturbed_problem(seed, n_arrays=6, trajectory=3, emission=0.0, spread=0.2):
    """A noisy scene and a start state = truth perturbed by ``spread`` m (arrays, sources)."""
    feats, truth = simulate_features(trajectory=trajectory, seed=seed, n_arrays=n_arrays)
    p = build_problem(feats, sigma_emit=emission)
    st = state_from_frames(p, truth["arrays"], truth["sources"]).copy()
    rng = np.random.default_rng(seed + 100)
    st.x[1:] += rng.normal(0, spread, st.x[1:].shape)
    st.s += rng.normal(0, spread, st.s.shape)
    return p, st, truth


def named(msg):
    """The parameters an ObservabilityError message names, as a set."""
    return set(msg.split("cannot determine ", 1)[1].split(" (")[0].split(", "))


# Parameter agreement in units of σ. With emission corrections the dense solver itself, started from two
# nearby points, stops 1.5e-6 σ apart (the cost is flat to its floating-point noise, ~1e-12 relative, over
# that distance), so there the bar is the solver's own reproducibility, 1e-5 σ.
@pytest.mark.slow
@pytest.mark.parametrize("seed,trajectory,emission,loss,tol", [(0, 3, 0.0, None, 1e-6), (1, 2, 0.0, "cauchy", 1e-6),
                                                                (3, 1, 0.0, None, 1e-6), (2, 1, 1e-3, None, 1e-5)])
def test_sparse_and_dense_solvers_reach_the_same_minimum(seed, trajectory, emission, loss, tol):
    p, st, _ = perturbed_problem(seed, trajectory=trajectory, emission=emission)
    kinds = KINDS + (["emission"] if emission else [])
    lay = make_layout(p)
    out = {d: levenberg_marquardt(p, st.copy(), lay, kinds, loss=loss, dense=d) for d in (True, False)}
    (sd_, id_), (ss, is_) = out[True], out[False]
    assert id_["converged"] and is_["converged"]
    assert abs(id_["cost"] - is_["cost"]) <= 1e-9 * id_["cost"]
    J = linearise(p, sd_, lay, kinds, dense=True).J
    sd = std_from_cov(p, lay, covariance(J, lay.n))
    for key in ("x", "s", "offset", "drift") + (("e",) if emission else ()):
        free = np.isfinite(sd[key])
        assert np.all(np.abs(getattr(sd_, key) - getattr(ss, key))[free] <= tol * sd[key][free]), key
    ang = (Rotation.from_matrix(sd_.R).inv() * Rotation.from_matrix(ss.R)).magnitude()
    assert np.all(ang[1:] <= tol * np.linalg.norm(sd["rot"][1:], axis=1))


def test_sparse_jacobian_equals_dense_and_factors_accept_dense_arrays():
    p, st, _ = perturbed_problem(4)
    lay = make_layout(p, emission=True)
    lin = linearise(p, st, lay, KINDS, dense=True)
    r1, Jd, c1 = lin.r, lin.J, lin.cost
    lin = linearise(p, st, lay, KINDS, dense=False)
    r2, Js, c2 = lin.r, lin.J, lin.cost
    assert scipy.sparse.issparse(Js) and not scipy.sparse.issparse(Jd)
    np.testing.assert_array_equal(Jd, Js.toarray())
    assert c1 == c2 and np.array_equal(r1, r2)
    # a factor written against a dense J (np.zeros + put) stacks the same way
    f = FACTORS["doa"](p, st, lay)
    assert np.array_equal(np.asarray(f.J), f.J.toarray()) and f.J.shape == (len(f.r), lay.n)


def test_block_covariance_matches_the_dense_inverse():
    p, st, _ = perturbed_problem(5, emission=1e-3)
    lay = make_layout(p)
    kinds = KINDS + ["emission"]
    Jd = linearise(p, st, lay, kinds, dense=True).J
    Js = linearise(p, st, lay, kinds, dense=False).J
    C = covariance(Jd, lay.n)
    B = covariance(Js, lay.n, lay)
    np.testing.assert_allclose(B.diagonal(), np.diag(C), rtol=1e-9)
    for ix in list(lay.x[1:]) + list(lay.rot[1:]) + list(lay.s):
        np.testing.assert_allclose(cov_block(B, ix), C[np.ix_(ix, ix)], rtol=1e-8, atol=1e-12 * np.abs(C).max())
    full = np.concatenate([lay.x[1:].ravel(), lay.offset[1:], lay.drift])
    np.testing.assert_allclose(cov_block(B, full), C[np.ix_(full, full)], rtol=1e-8,
                               atol=1e-10 * np.abs(C[np.ix_(full, full)]).max())
    # draws H⁻¹ Jᵀ z have exactly the covariance: sample variance within 4 standard errors
    rng = np.random.default_rng(0)
    S = np.array([B.sample(rng) for _ in range(3000)])
    z = (S.var(0) / np.diag(C) - 1.0) / np.sqrt(2.0 / len(S))
    assert np.mean(np.abs(z) < 4) > 0.99


def test_sparse_observability_agrees_with_the_dense_svd():
    feats, truth = simulate_features(trajectory=3, seed=2, n_arrays=6)
    p = build_problem(feats)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    lay = make_layout(p)
    for dense in (True, False):
        check_observability(p, lay, KINDS, st, dense=dense)  # a full scene is observable
    # array A3 without TDOA-S and with one TDOA-M: its drift and offset cannot be told apart
    f2 = dict(feats)
    f2["tdoa_s"] = feats["tdoa_s"][feats["tdoa_s"]["array"] != "A3"]
    tm = feats["tdoa_m"]
    f2["tdoa_m"] = tm[(tm["array"] != "A3") | (tm["event"] == 0)]
    found = []
    for dense in (True, False):   # reported undetermined (not refused), the same parameters either way
        q = build_problem(f2)
        q = check_observability(q, make_layout(q), KINDS, st, dense=dense)
        found.append({(u["array"], u["parameter"]) for u in q.unobservable})
        assert make_layout(q).n == make_layout(p).n - 1   # one column out: the null space is 1-D
    assert found[0] == found[1] == {("A3", "drift"), ("A3", "offset")}


def test_sparse_observability_names_an_unlocatable_source():
    # event 5 seen only by the reference array's DOA: with odometry off its source is a ray, range unknown
    feats, truth = simulate_features(trajectory=3, seed=3, n_arrays=5)
    f2 = dict(feats)
    f2["tdoa_m"] = feats["tdoa_m"][feats["tdoa_m"]["event"] != 5]
    f2["doa"] = feats["doa"][(feats["doa"]["event"] != 5) | (feats["doa"]["array"] == "A1")]
    f2["tdoa_s"] = feats["tdoa_s"][~feats["tdoa_s"]["from_event"].isin([4, 5])]
    p = build_problem(f2)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    lay = make_layout(p)
    kinds = ["tdoa_s", "tdoa_m", "doa"]  # no odometry
    msgs = []
    for dense in (True, False):
        with pytest.raises(ObservabilityError, match="event 5") as e:
            check_observability(p, lay, kinds, st, dense=dense)
        msgs.append(str(e.value))
    assert named(msgs[0]) == named(msgs[1])


@pytest.mark.slow
def test_array_covariance_of_a_large_problem_is_the_dense_inverse_block():
    # calibration.json's covariance (estimator.array_covariance) on a problem past the dense limit: the
    # sparse block inverse, not a dense n x n pinv of the whole Jacobian (11 GB at 40 arrays x 1000 events)
    from calib.estimator import array_covariance
    from calib.estimator.solver import use_dense
    from calib.estimator.uncertainty import inflated_rows
    from calib.estimator.variance import covariance_factors

    rng = np.random.default_rng(7)
    stops = np.cumsum(rng.normal(0, 0.4, (90, 3)), axis=0) * [1, 1, 0.2] + [0, 0, 1.2]
    feats, truth = simulate_features(trajectory=stops, seed=7, n_arrays=5)
    p = build_problem(feats)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    lay = make_layout(p)
    assert not use_dense(lay)
    labels, cov = array_covariance({"problem": p, "state": st, "layout": lay, "kinds": KINDS, "mask": {}})
    # the honest covariance (uncertainty.honest_covariance): each array's rows with the σ² factor of its
    # residuals (large problems: without leverages), the same factors on the dense Jacobian
    factors = covariance_factors(p, linearise(p, st, lay, KINDS), None)
    J = inflated_rows(p, linearise(p, st, lay, KINDS, dense=True), factors)
    idx = np.concatenate([np.r_[lay.x[i], lay.rot[i], lay.offset[i], lay.drift[i]] for i in range(len(p.names))])
    idx = idx[idx >= 0]
    ref = covariance(J, lay.n)[np.ix_(idx, idx)]
    assert len(labels) == len(idx)
    np.testing.assert_allclose(cov, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())


def test_memory_check_counts_the_sparse_jacobian_and_refuses_only_what_cannot_fit(monkeypatch):
    from calib.errors import InputError
    from calib.pipeline.formats import validate as V

    # the Jacobian width per row bounds the factors' real non-zeros (within 25 %: the reference array's
    # fixed columns are the difference)
    rng = np.random.default_rng(3)
    stops = np.cumsum(rng.normal(0, 0.4, (90, 3)), axis=0) * [1, 1, 0.2] + [0, 0, 1.2]
    feats, truth = simulate_features(trajectory=stops, seed=3, n_arrays=8)
    p = build_problem(feats)
    J = linearise(p, state_from_frames(p, truth["arrays"], truth["sources"]), make_layout(p), KINDS,
                  dense=False).J
    rows = {"tdoa_m": len(feats["tdoa_m"]), "tdoa_s": len(feats["tdoa_s"]), "doa": 3 * len(feats["doa"])}
    bound = V.jacobian_entries(p.K, rows)
    assert 0.75 * bound <= J.nnz <= bound
    # 40 arrays x 1000 events (issue 32: refused before as "6.62 GiB"): about 0.4 GiB (measured 358 MB), accepted on 1 GiB
    big = {"tdoa_m": 39 * 1000, "tdoa_s": 40 * 999, "doa": 3 * 40 * 1000}
    assert 0.3 * 2**30 < V.estimator_memory(1000, 40, big) < 0.7 * 2**30
    monkeypatch.setattr(V, "memory_limit", lambda: 2**30)
    V.check_problem_size(1000, 40, big, "features")
    monkeypatch.setattr(V, "memory_limit", lambda: 2**28)
    with pytest.raises(InputError, match=r"features: 1000 events × 40 arrays .* need about 0\.\d+ GiB .* 0\.25 GiB"):
        V.check_problem_size(1000, 40, big, "features")


@pytest.mark.parametrize("n, u", [(1, 0), (6, 2), (60, 5), (200, 7)])
def test_banded_inverse_band_and_half_solve_equal_the_dense_inverse(n, u):
    """_BandedSPD.inverse_band (Takahashi's recurrence) reads the band of (A + λI)⁻¹ that np.linalg.inv gives;
    half_solve's |U⁻ᵀ b|² is bᵀ (A + λI)⁻¹ b (the Schur complement's reduction)."""
    from calib.estimator.solver import _BandedSPD

    rng = np.random.default_rng(n + u)
    M = np.zeros((n, n))
    for d in range(1, u + 1):
        v = rng.normal(size=n - d)
        M += np.diag(v, d) + np.diag(v, -d)
    M += np.diag(np.abs(M).sum(axis=1) + rng.uniform(0.1, 1.0, n))   # diagonally dominant: SPD
    f = _BandedSPD(scipy.sparse.csr_matrix(M), 0.01, u)
    Z = np.linalg.inv(M + 0.01 * np.eye(n))
    want = np.array([[Z[i, i + k] if i + k < n else 0.0 for k in range(u + 1)] for i in range(n)])
    np.testing.assert_allclose(f.inverse_band(), want, rtol=0, atol=1e-13 * np.abs(Z).max())
    B = rng.normal(size=(n, 4))
    Y = f.half_solve(B)
    np.testing.assert_allclose(Y.T @ Y, B.T @ Z @ B, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("n_stops", [12, pytest.param(90, marks=pytest.mark.slow)])
def test_calibration_carries_the_covariance_the_std_columns_come_from(n_stops, tmp_path):
    # calibrate() computes the array covariance once, with the std columns; calibration.json writes it. It must
    # be the one a calibration read back from disk gives (estimator.rebuild + array_covariance), and its
    # diagonal the squared std columns; dense (12 stops) and sparse (90 stops, past the dense limit) alike
    from calib.estimator import array_covariance, calibrate, rebuild
    from calib.pipeline.formats.io import read_calibration, write_calibration

    rng = np.random.default_rng(11)
    stops = np.cumsum(rng.normal(0, 0.4, (n_stops, 3)), axis=0) * [1, 1, 0.2] + [0, 0, 1.2]
    feats, _ = simulate_features(trajectory=stops, seed=11, n_arrays=5)
    cal = calibrate(feats)
    labels, cov = cal["array_covariance"]
    write_calibration(tmp_path / "c", cal, features=feats)
    back = read_calibration(tmp_path / "c")
    labels2, cov2 = array_covariance(rebuild(feats, back))
    # the reference's drift, then 4 free arrays x (3 position, 3 rotation, offset, drift)
    assert labels == labels2 and len(labels) == 1 + 4 * 8
    sd = np.sqrt(np.diag(cov2))   # (each entry in units of its parameters' std: m, rad and s mix)
    np.testing.assert_allclose(cov / np.outer(sd, sd), cov2 / np.outer(sd, sd), rtol=0, atol=1e-5)
    std = {f"{r['array']}.{c}": r[f"{c}_std"] for _, r in cal["arrays"].iterrows() for c in ("x", "y", "z")}
    for k, lab in enumerate(labels):
        if lab in std:
            assert np.sqrt(cov[k, k]) == pytest.approx(std[lab], rel=1e-9)
