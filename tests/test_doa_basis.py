"""A DOA row's treatment must not depend on an arbitrary basis of its tangent plane: the whitening axes of a row
whose two tangent stds are (nearly) equal (a regular tetrahedron's always, a planar board's toward its normal) are
no property of the data, so the estimate and its stated stds must not move when a 1e-8 jitter turns them."""
import numpy as np
import pytest

from calib.estimator import calibrate
from calib.estimator.problem import DoaRows, canonical_tangents, doa_axes
from calib.pipeline.simulate.featsim import simulate_features

TETRA = [[0.05, 0.05, 0.05], [0.05, -0.05, -0.05], [-0.05, 0.05, -0.05], [-0.05, -0.05, 0.05]]
CIRCLE6 = [[0.0463 * np.cos(a), 0.0463 * np.sin(a), 0.0] for a in np.arange(6) * np.pi / 3]
JITTER = 1e-8   # far below any DOA's noise (5° here): numerical noise, which no error bar may follow


def _rows(u):
    n = len(u)
    return DoaRows(ev=np.arange(n), arr=np.zeros(n, int), u=u, row=np.arange(n), scale=np.ones(n),
                   axes=np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), axis_scale=np.ones((n, 3)))


def _directions(rng, n):
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def test_isotropic_rows_take_a_basis_that_follows_their_direction():
    """A tetrahedron's rows (tangent variances equal up to rounding): axes orthonormal, the tangent pair the
    canonical az/el one (continuous in u: a 1e-8 jitter turns it by ~1e-8), scales one. A planar board's rows
    away from its normal keep their principal axes and the elevation's larger sigma."""
    rng = np.random.default_rng(500)
    u = _directions(rng, 50)
    v = u + rng.normal(0, JITTER, u.shape)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    meta = {"mics": {"A": TETRA}}
    a, b = (doa_axes(_rows(x), meta, np.array(["A"]), 1e-4) for x in (u, v))
    assert np.allclose(a.axes @ np.transpose(a.axes, (0, 2, 1)), np.eye(3), atol=1e-12)
    assert np.allclose(a.axes[:, :2], canonical_tangents(u, [0, 0, 1]))
    assert np.max(np.abs(a.axes - b.axes)) < 1e-6
    assert np.allclose(a.axis_scale, 1.0)
    tilted = u[np.abs(u[:, 2]) < 0.7]   # ≥ 45° from the normal: elevation at least √2 × the azimuth's sigma
    c = doa_axes(_rows(tilted), {"mics": {"A": CIRCLE6}}, np.array(["A"]), 1e-4)
    assert np.all(c.axis_scale[:, 1] > 1.3)
    assert np.allclose(np.abs(np.einsum("ka,ka->k", c.axes[:, 0], np.cross([0, 0, 1], tilted))),
                       np.linalg.norm(np.cross([0, 0, 1], tilted), axis=1), atol=1e-6)   # axis 0: the azimuth


def test_canonical_tangents_off_and_on_the_axis():
    u = np.array([[1.0, 0, 0], [0, 0, 1.0], [0.6, 0, 0.8]])
    t = canonical_tangents(u, [0, 0, 1])
    assert np.allclose(np.einsum("kia,ka->ki", t, u), 0) and np.allclose(np.linalg.norm(t, axis=2), 1)
    assert np.allclose(t[0, 1], [0, 0, 1]) and np.allclose(t[2, 1], [-0.8, 0, 0.6])   # toward the axis
    assert np.all(np.isfinite(t[1]))   # on the axis: the x axis stands in


@pytest.mark.parametrize("seed", [500, 501])
def test_stated_stds_do_not_follow_a_1e8_doa_jitter(seed):
    """Independent truth: the jitter is 1e-8 rad where the DOAs' noise is 5°, so the calibration is the same
    one; its estimate and stated stds must agree to 1e-4 (on main a tetrahedron's rows were whitened along
    eigenvectors set by rounding, the robust loss and the residuals' lag correlation read in them, and the
    planar arrays' az/el error model dotted array-frame directions with residuals in those axes)."""
    feats, _ = simulate_features(3, seed=seed)
    names = feats["meta"]["arrays"]
    feats = feats.replace(meta={**feats["meta"], "mics": {a: (TETRA if k % 2 else CIRCLE6) for k, a in enumerate(names)}})
    rng = np.random.default_rng(seed)
    d = feats["doa"].copy()
    u = d[["ux", "uy", "uz"]].to_numpy() + rng.normal(0, JITTER, (len(d), 3))
    d[["ux", "uy", "uz"]] = u / np.linalg.norm(u, axis=1, keepdims=True)
    a, b = (calibrate(f, target_position=0, target_orientation_deg=0)["arrays"].set_index("array")
            for f in (feats, feats.replace(doa=d)))
    std = [c for c in a.columns if c.endswith("_std")]
    rel = np.abs(b[std].to_numpy() / a[std].to_numpy() - 1)
    assert np.nanmax(rel) < 1e-4
    assert np.max(np.abs(b[["x", "y", "z"]].to_numpy() - a[["x", "y", "z"]].to_numpy())) < 1e-5


def test_doa_lag_correlation_is_read_in_the_array_frame():
    """Residuals drifting along the trajectory (a random walk of the array-frame error, true lag-1 correlation
    near 1) inflate the array's factor the same whatever tangent axes each row is whitened along: turning every
    row's pair by a random angle (its residual turned with it) leaves the inflation as it was."""
    from types import SimpleNamespace
    from calib.estimator.problem import build_problem
    from calib.estimator.variance import _correlation_inflation
    feats, _ = simulate_features(3, seed=502)
    feats = feats.replace(meta={**feats["meta"], "mics": {a: TETRA for a in feats["meta"]["arrays"]}})
    p = build_problem(feats)
    rng = np.random.default_rng(502)
    m = len(p.doa.arr)
    drift = np.zeros((m, 3))
    for i in range(p.N):   # per array, in event order: a random walk
        k = np.flatnonzero(p.doa.arr == i)
        drift[k[np.argsort(p.doa.ev[k])]] = np.cumsum(rng.normal(size=(len(k), 3)), axis=0)
    f, keep = SimpleNamespace(kind="doa", dim=3), np.ones(3 * m, bool)

    def inflation(axes):
        q = p.replace(doa=__import__("dataclasses").replace(p.doa, axes=axes))
        return _correlation_inflation(q, f, np.einsum("kab,kb->ka", axes, drift).ravel(), keep)

    a = rng.uniform(0, 2 * np.pi, m)
    turn = np.zeros((m, 3, 3))
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1], turn[:, 2, 2] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a), 1
    base = inflation(p.doa.axes)
    assert np.all(base[np.unique(p.doa.arr)] > 1.2)   # the drift is seen
    assert np.allclose(inflation(turn @ p.doa.axes), base, rtol=1e-12)


def test_planar_model_at_the_stated_variances_is_the_plain_information():
    """Analytic identity: the planar arrays' error model (``planar_doa_rows``' rows, read back in the array frame)
    given the very variances along azimuth and elevation that the rows' whitening states gives back the plain
    information JᵀJ of their tangent components (on main it mixed array-frame directions with whitened axes)."""
    from calib.estimator.factors import active_kinds
    from calib.estimator.problem import make_layout
    from calib.estimator.solver import linearise
    from calib.estimator import uncertainty as U
    feats, _ = simulate_features(3, seed=503)
    feats = feats.replace(meta={**feats["meta"], "mics": {a: CIRCLE6 for a in feats["meta"]["arrays"]}})
    cal = calibrate(feats, target_position=0, target_orientation_deg=0)
    p, st = cal["problem"], cal["state"]
    lin = linearise(p, st, make_layout(p), active_kinds(p))
    f, start, n = next(U._kind_blocks(lin, "doa"))
    _, J, _ = U._array_frame_rows(p, lin, f, start, n)
    nv, u = U.plane_normals(feats["meta"], p.names)[p.doa.arr], p.doa.u
    e_el = nv - np.einsum("ka,ka->k", nv, u)[:, None] * u
    e_el /= np.linalg.norm(e_el, axis=1, keepdims=True)
    e_az = np.cross(u, e_el)
    C = np.einsum("kba,kb,kbc->kac", p.doa.axes, p.doa.axis_scale ** 2, p.doa.axes)   # stated, in sig0² units
    assert np.ptp(p.doa.axis_scale[:, 1]) > 0.1   # the rows' elevations are whitened apart from their azimuths
    G = [np.sqrt(np.einsum("ka,kab,kb->k", e, C, e))[:, None] * np.einsum("ka,kan->kn", e, J) for e in (e_az, e_el)]
    Jw = lin.J[start:start + n]
    Jw = (Jw.toarray() if hasattr(Jw, "toarray") else np.asarray(Jw)).reshape(n // 3, 3, -1)[:, :2]
    plain = np.einsum("kin,kim->nm", Jw, Jw)
    assert np.abs(G[0].T @ G[0] + G[1].T @ G[1] - plain).max() < 1e-9 * np.abs(plain).max()
