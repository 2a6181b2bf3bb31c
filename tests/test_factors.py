"""Every factor's analytic Jacobian against central finite differences (on the manifold for rotations)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.estimator.factors import FACTORS
from calib.estimator.problem import build_problem, make_layout, retract, state_from_dict
from calib.pipeline.simulate.featsim import simulate_features


def random_state(p, rng):
    N, K = p.N, p.K
    return state_from_dict({"x": rng.normal(0, 2, (N, 3)), "R": Rotation.random(N, random_state=rng).as_matrix(),
                            "offset": rng.normal(0, 0.05, N), "drift": rng.normal(0, 1e-4, N),
                            "s": rng.normal(0, 2, (K, 3)), "e": rng.normal(0, 1e-3, K)})


@pytest.mark.parametrize("kind,planar", [(k, None) for k in FACTORS] + [("doa", (0.3, -0.2, 0.9))])
def test_jacobian_matches_central_differences(kind, planar):
    feats, _ = simulate_features(trajectory=3, seed=1, planar=planar)
    if kind == "cone":   # array A3 as a linear array along its y axis (roll about y not in the layout)
        feats["meta"]["doa_axes"] = {"A3": [0, -1, 0]}
    check_jacobian(feats, kind)


def check_jacobian(feats, kind, seed=3):
    """``kind``'s analytic Jacobian on ``feats`` at a random state against central differences (every
    parameter free, emission corrections included). Also used for kinds registered by other tests."""
    rng = np.random.default_rng(seed)
    feats = {**feats, "meta": {**feats["meta"], "chirp_drift_bias": 0.3}}
    p = build_problem(feats, sigma_emit=1e-3)
    st = random_state(p, rng)
    lay = make_layout(p, emission=True, ref_drift=True)
    f = FACTORS[kind](p, st, lay)
    J = np.asarray(f.J)
    assert J.shape == (len(f.r), lay.n) and len(f.r) > 0
    num = np.zeros_like(J)
    clock_cols = {int(c) for key in ("drift", "offset", "e") for c in getattr(lay, key).ravel() if c >= 0}
    for k in range(lay.n):
        h = np.zeros(lay.n)
        # steps scaled to each parameter's natural size; residuals are affine in clocks, so large steps
        # there only avoid cancellation (residuals reach ~1e6 with t ~ 100 s and sigma 1e-4 s)
        h[k] = 1e-4 if k in clock_cols else 1e-6
        num[:, k] = (FACTORS[kind](p, retract(st, lay, h), lay).r
                     - FACTORS[kind](p, retract(st, lay, -h), lay).r) / (2 * h[k])
    scale = np.maximum(np.abs(num).max(axis=0), 1e-6)
    np.testing.assert_allclose(J / scale, num / scale, atol=2e-5)
    assert np.abs(J).sum() > 0


def test_a_doa_rows_own_sigma_scales_its_residuals_and_jacobian_rows():
    """doa.csv's sigma_deg: each row's residuals and Jacobian rows divided by √(½ + ½ (σ_row / σ)²) (σ the
    type's sigma_doa_deg), against the same problem without the column; rows without a value unchanged."""
    from calib.estimator.problem import DOA_ROW_WEIGHT

    assert DOA_ROW_WEIGHT == 0.5
    rng = np.random.default_rng(4)
    feats, _ = simulate_features(trajectory=3, seed=1)
    p0 = build_problem(feats)
    own = rng.uniform(0.1, 5.0, len(feats["doa"]))
    own[::4] = np.nan
    feats["doa"]["sigma_deg"] = own
    p1 = build_problem(feats)
    st = random_state(p0, rng)
    lay = make_layout(p0)
    f0, f1 = FACTORS["doa"](p0, st, lay), FACTORS["doa"](p1, st, lay)
    want = np.sqrt(0.5 + 0.5 * (own / feats["meta"]["sigma_doa_deg"]) ** 2)
    want = np.repeat(np.where(np.isnan(own), 1.0, want), 3)
    np.testing.assert_allclose(f1.r * want, f0.r, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(f1.J) * want[:, None], np.asarray(f0.J), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(f1.row_sigma, f0.sigma * want, rtol=1e-12)
