"""Every factor's analytic Jacobian against central finite differences (on the manifold for rotations)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.estimator.factors import FACTORS
from calib.estimator.problem import SourceMotion, build_problem, make_layout, retract, state_from_dict
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
    # (the velocity prior: only a moving source has one; the speed of sound's: only a free c)
    check_jacobian(feats, kind, moving=kind == "velocity", speed=kind == "speed")


@pytest.mark.parametrize("curve", [False, True])
@pytest.mark.parametrize("kind", ["tdoa_s", "tdoa_m", "doa", "cone"])
def test_a_moving_source_s_factors_keep_the_jacobian_exact(kind, curve):
    """A source moving during the sweep (``problem.SourceMotion``): the arrival shifts β ṙ/c (or a measured
    curve) inside the TDOA factors with their derivatives in source, array position and odometry yaw, and the
    velocity error's nuisance in the TDOA and turned DOA rows."""
    feats, _ = simulate_features(trajectory=3, seed=1)
    if kind == "cone":
        feats["meta"]["doa_axes"] = {"A3": [0, -1, 0]}
    check_jacobian(feats, kind, moving="curve" if curve else True)


CIRCLE6 = [[0.0463 * np.cos(a), 0.0463 * np.sin(a), 0.0] for a in np.arange(6) * np.pi / 3]


@pytest.mark.parametrize("planar", [None, (0.3, -0.2, 0.9)])
def test_doa_jacobian_with_per_row_axes(planar):
    """The DOA factor whitened along each row's own axes (meta ``mics``: planar 6-mic circles, one array a
    tetrahedron), mirror-ambiguous arrays or not."""
    feats, _ = simulate_features(trajectory=3, seed=1, planar=planar)
    tetra = [[0.05, 0.05, 0.05], [0.05, -0.05, -0.05], [-0.05, 0.05, -0.05], [-0.05, -0.05, 0.05]]
    feats["meta"]["mics"] = {a: (tetra if k == 1 else CIRCLE6) for k, a in enumerate(feats["meta"]["arrays"])}
    p = build_problem(feats)
    assert np.ptp(p.doa.axis_scale[:, :2]) > 0.1   # the axes differ between rows: the test sees them
    check_jacobian(feats, "doa")


def check_jacobian(feats, kind, seed=3, moving=False, speed=False):
    """``kind``'s analytic Jacobian on ``feats`` at a random state against central differences (every
    parameter free, emission corrections included; ``moving``: a source moving during the sweep, its velocity
    error and the odometry yaw free too, "curve": its shifts from a measured curve; ``speed``: the speed of
    sound free too). Also used for kinds registered by other tests."""
    rng = np.random.default_rng(seed)
    feats = {**feats, "meta": {**feats["meta"], "chirp_drift_bias": 0.3}}
    p = build_problem(feats, sigma_emit=1e-3)
    st = random_state(p, rng)
    if moving:
        x = np.linspace(-0.02, 0.02, 9)
        p = p.replace(motion=SourceMotion(rng.normal(0, 0.8, (p.K, 3)), rng.normal(0, 0.2, (p.K, 3)),
                                          (x, 0.5 * x + 20 * x**2) if moving == "curve" else None, p.beta, 0.05, 0.2),
                      sigma={**p.sigma, "velocity": 0.05}, odo_yaw_free=True)
        st.odo_yaw, st.dv = np.array([0.3]), rng.normal(0, 0.05, (p.K, 3))
    if speed:   # the speed of sound free (estimator/soundspeed.py), away from the declared value
        p = p.replace(c_free=True, sigma={**p.sigma, "speed": 0.01})
        st.cs = np.array([0.02])
    lay = make_layout(p, emission=True, ref_drift=True)
    f = FACTORS[kind](p, st, lay)
    J = np.asarray(f.J)
    assert J.shape == (len(f.r), lay.n) and len(f.r) > 0
    num = np.zeros_like(J)
    # (and the velocity errors: a step of 1e-6 m/s moves a source by β × that, lost in the residuals' rounding)
    clock_cols = {int(c) for key in ("drift", "offset", "e", "dv") for c in getattr(lay, key).ravel() if c >= 0}
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
    """doa.csv's sigma_deg: each row's residuals and Jacobian rows divided by √(½ (m / σ)² + ½ (σ_row / σ)²)
    (σ the type's sigma_doa_deg, m the median row's sigma_deg), against the same problem without the column;
    rows without a value unchanged."""
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
    typ, med = feats["meta"]["sigma_doa_deg"], np.nanmedian(own)
    want = np.sqrt(0.5 * (med / typ) ** 2 + 0.5 * (own / typ) ** 2)
    want = np.repeat(np.where(np.isnan(own), 1.0, want), 3)
    np.testing.assert_allclose(f1.r * want, f0.r, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(f1.J) * want[:, None], np.asarray(f0.J), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(f1.row_sigma, f0.sigma * want, rtol=1e-12)


@pytest.mark.parametrize("typical", [0.05, 0.5, 5.0])
def test_a_doa_rows_sigma_is_shrunk_toward_the_median_row_whatever_the_tail(typical):
    """The rows' own sigmas span 100× (near-plane rows of planar arrays, reflections): shrunk toward the type's
    sigma (the frontend's RMS, which follows the few largest) the hall's and lab's precise rows were weighed
    as 3–5× their claim. Shrunk toward the median row's, a row's sigma is √(½ m² + ½ σ_row²) whatever the
    type's sigma, one tail row, or a flagged row; rows without a value keep the type's sigma."""
    import pandas as pd
    from calib.estimator.problem import doa_row_scales

    own = np.r_[np.full(9, 0.06), np.full(5, 0.6), 1.6, 25.0, np.nan]   # precise, near-plane, tail, flagged, cone
    flag = [""] * 15 + ["doa_spread", ""]
    doa = pd.DataFrame({"sigma_deg": own, "flag": flag})
    sigma = typical * doa_row_scales(doa, {"sigma_doa_deg": typical})
    m = 0.06   # the median of the 15 clean rows
    np.testing.assert_allclose(sigma[:16], np.sqrt(0.5 * m**2 + 0.5 * own[:16] ** 2), rtol=1e-12)
    assert sigma[0] == pytest.approx(0.06) and sigma[-1] == pytest.approx(typical)


@pytest.mark.parametrize("elev_deg", [6.0, 40.0, -25.0])
def test_doa_axes_follow_a_planar_fits_errors(elev_deg):
    """A 6-mic circle's DOAs from noisy mic times (least-squares plane wave on the in-plane slowness, the
    normal part from |u| = 1): the errors along ``doa_axes``' two tangent axes have the std ratio it states
    (elevation/azimuth ≈ 1/|u·n| near the plane, ≈ 1 far from it), and the better axis is the azimuth."""
    from calib.estimator.problem import DoaRows, doa_axes

    rng = np.random.default_rng(7)
    mics, c, n = np.array(CIRCLE6), 343.0, 4000
    el, az = np.radians(elev_deg), np.radians(30.0)
    u = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    t = -(mics @ u) / c + rng.normal(0, 2e-8, (n, len(mics)))       # plane wave + timing noise
    A = np.column_stack([np.ones(len(mics)), -mics[:, :2] / c])
    v = np.linalg.lstsq(A, t.T, rcond=None)[0][1:].T                 # (n, 2) in-plane part
    est = np.column_stack([v, np.sign(u[2]) * np.sqrt(np.clip(1 - (v ** 2).sum(axis=1), 0, None))])
    rows = DoaRows(np.zeros(1, int), np.zeros(1, int), u[None], np.zeros(1, int), np.ones(1), np.eye(3)[None],
                   np.ones((1, 3)))
    out = doa_axes(rows, {"mics": {"A": CIRCLE6.copy()}}, np.array(["A"]), 1e-6)
    B, f = out.axes[0], out.axis_scale[0]
    sd = (est - u) @ B[:2].T
    ratio = np.std(sd[:, 1]) / np.std(sd[:, 0])
    assert f[0] == 1.0 and f[2] == 1.0
    assert ratio == pytest.approx(f[1], rel=0.1)
    assert abs(B[0] @ np.array([-np.sin(az), np.cos(az), 0.0])) > 0.99    # the azimuth axis
    if abs(elev_deg) < 10:
        assert f[1] > 5.0


@pytest.mark.parametrize("case", ["mirror", "mics", "moving", "cone"])
def test_doa_and_cone_rows_as_steered_with_the_declared_speed_keep_the_jacobian_exact(case):
    """c free and moved (ln c/c_declared = 0.02): a planar array's DOA prediction has its in-plane part scaled by
    e^{−κ} (planar from ``doa_mirror_normals`` or from its mics in meta, a 3-D board unchanged), a linear
    array's cos θ too; their derivatives in κ and in the rest against central differences."""
    planar = (0.3, -0.2, 0.9) if case == "mirror" else None
    feats, _ = simulate_features(trajectory=3, seed=1, planar=planar)
    if case == "mics":
        tetra = [[0.05, 0.05, 0.05], [0.05, -0.05, -0.05], [-0.05, 0.05, -0.05], [-0.05, -0.05, 0.05]]
        feats["meta"]["mics"] = {a: (tetra if k == 1 else CIRCLE6) for k, a in enumerate(feats["meta"]["arrays"])}
    if case == "cone":
        feats["meta"]["doa_axes"] = {"A3": [0, -1, 0]}
    check_jacobian(feats, "cone" if case == "cone" else "doa", moving=case == "moving", speed=True)


def test_the_steered_doa_prediction_is_the_frontends_and_vanishes_at_the_declared_speed():
    """The factor's prediction at κ ≠ 0 equals calib.geometry.steered_doas of the true direction (the frontend's
    planar completion), its residual is zero on DOAs so made; at κ = 0 with c not free the factor is the plain
    one bit for bit."""
    from calib.estimator.factors import _planar_steering
    from calib.geometry import steered_doas

    rng = np.random.default_rng(7)
    feats, _ = simulate_features(trajectory=3, seed=1, planar=(0.0, 0.0, 1.0))
    p = build_problem(feats)
    st = random_state(p, rng)
    st.cs = np.array([np.log(349.0 / 343.0)])
    v = rng.normal(size=(50, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    got = _planar_steering(p, st, np.zeros(50, int), v).q
    np.testing.assert_allclose(got, steered_doas(v, 343.0 / 349.0, normal=(0.0, 0.0, 1.0)), atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(got[:, 2] * np.sign(v[:, 2]) >= np.abs(v[:, 2]), True)   # elevation raised
    st.cs = np.zeros(1)
    lay = make_layout(p)
    plain = FACTORS["doa"](p.replace(plane=None), st, lay)
    np.testing.assert_array_equal(FACTORS["doa"](p, st, lay).r, plain.r)
