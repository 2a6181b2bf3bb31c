"""Issue 27: the error of the velocity a moving source's correction uses, in the error bars
(``estimator.motion.MotionNoise``, ``uncertainty.velocity_rows``).

Truth is independent of the code under test: the rows' sensitivity to the velocity is checked by finite
differences of the correction itself (``motion.corrected``), the covariance against the spread of estimates
whose velocity errors are drawn from the stated sigma, and ``velocity_sigma`` against a trajectory whose
acceleration is known.
"""
import numpy as np
import pytest

from calib.estimator import calibrate
from calib.estimator.factors import active_kinds
from calib.estimator.motion import MotionNoise, corrected, doa_moves, velocity_sigma
from calib.estimator.problem import build_problem, make_layout
from calib.estimator.solver import linearise
from calib.estimator.uncertainty import state_from_frames, velocity_rows
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features
from .sessions import NO_TARGET

def _moving(feats, truth, vel_error=None):
    """Features of a robot moving while it chirps (arrivals shifted by β ṙ/c at the true velocity), events.csv
    carrying the velocity + ``vel_error`` (the odometry's error): test_motion_nlos's scene."""
    from .test_motion_nlos import _moving as moving
    return moving(feats, truth, with_vel=True, vel_error=vel_error)[0]


def _whitened(p, st, lay, kinds):
    return linearise(p, st, lay, kinds).r


@pytest.mark.parametrize("seed", [0, 3])
def test_velocity_rows_are_the_corrections_derivative(seed):
    """Finite differences of the corrected arrivals (and of the turned DOAs) against the solve's velocity-error
    columns (``State.dv``: the arrivals see the source at s + β δv, DOAs turned from t_doa at s + t_doa δv),
    at the truth of noise-free features (a measured DOA off the predicted one turns the normalisation by its
    error: 1-2 % at 1°); with them in the solve, ``velocity_rows`` adds nothing (no double count)."""
    import dataclasses

    f, tr = simulate_features(2, 2e-5, 1.0, 0.01, seed=seed, noise=False)
    g = _moving(f, tr)
    p = build_problem(g)
    st = state_from_frames(p, tr["arrays"], tr["sources"])
    vel = np.array(g["events"][["vel_x", "vel_y", "vel_z"]], float)
    pc = corrected(p, st, vel)
    lay, kinds = make_layout(pc), active_kinds(pc)
    lin = linearise(pc, st, lay, kinds)
    # the same problem with the velocity error modelled (t_doa 1 s: its DOA columns per m); δv = 0 at st
    pv = pc.replace(motion=dataclasses.replace(pc.motion, sigma=1.0, t_doa=1.0), sigma={**pc.sigma, "velocity": 1.0})
    lay_v = make_layout(pv)
    lin_v = linearise(pv, st, lay_v, active_kinds(pv))
    assert velocity_rows(lin_v, lay_v, MotionNoise(1.0, p.beta, 1.0)) is None
    A = np.asarray(lin_v.J)[:len(lin.r), lay_v.dv.ravel()]   # per m/s (arrivals), per m (DOAs); (prior rows last)
    np.testing.assert_array_equal(lin_v.r[:len(lin.r)], lin.r)
    r0 = lin.r
    doa = np.zeros(len(r0), bool)
    start = 0
    for fac in lin.factors:
        doa[start:start + len(fac.r)] = fac.kind == "doa"
        start += len(fac.r)
    h = 1e-3
    for j, c in ((1, 0), (p.K // 2, 2), (p.K - 2, 1)):
        dv = np.zeros_like(vel)
        dv[j, c] = h
        num = (_whitened(corrected(p, st, vel + dv), st, lay, kinds) - r0) / h
        assert np.allclose(num[~doa], A[~doa, 3 * j + c], rtol=1e-3, atol=1e-3 * np.abs(A[~doa]).max())   # (1 + drift) of the clocks: 1e-4
        # the DOAs: turned by a displacement that is h off along c
        disp = np.zeros_like(vel)
        u = p.doa.u + doa_moves(p, st, disp + dv, p.doa.arr, p.doa.ev, p.doa.u)
        pd_ = pc.replace(doa=pc.doa.__class__(**{**vars(pc.doa), "u": u / np.linalg.norm(u, axis=1)[:, None]}))
        num = (_whitened(pd_, st, lay, kinds) - r0) / h
        assert np.allclose(num[doa], A[doa, 3 * j + c], rtol=2e-2, atol=1e-3 * np.abs(A[doa]).max())


@pytest.mark.slow
def test_velocity_error_covered_by_the_stated_sigma(monkeypatch):
    """Velocity errors drawn from σ_v (0.05 m/s per axis, β σ_v ≈ 3 cm of source shift per event, well above
    the other noise): the arrays' position errors over seeds against their stated std — with the velocity
    error in the solve (``State.dv``) the error / std RMS is near 1 (0.82), over the sessions whose verdict is
    not ``failed`` (the error bars are a claim of those), at least 10 of 12 (with the error only in the error
    bars and the shifts fixed between passes, seeds 2, 8 and 9 failed; seed 9 still does: its reference's DOAs
    thousands of σ off the first solve, on main too). Linear clocks: the clock selection ends linear on these
    seeds (tests/test_clocks.py checks that on a moving session). (Its earlier half, the std without the
    velocity term claiming far too much, has no counterpart once the term is in the solve: with σ_v stated as
    1e-6 the variance factors of the misfit widen the std instead, error / std 0.37.)"""
    import calib.estimator.motion as motion
    sigma_v = 0.05
    monkeypatch.setattr(motion, "velocity_sigma", lambda *a, **k: sigma_v)
    z_with = []
    for seed in range(12):
        f, tr = simulate_features(2, 2e-6, 0.05, 0.01, seed=seed)
        rng = np.random.default_rng(100 + seed)
        g = _moving(f, tr, vel_error=rng.normal(0.0, sigma_v, (len(f["events"]), 3)))
        out = calibrate(g, noise="meta", clock_model="linear")
        assert out["report"]["stages"]["motion"]["velocity_sigma_m_s"] == sigma_v
        if out["report"]["verdict"]["status"] == "failed":
            continue
        est = out["arrays"].set_index("array")
        truth = tr["arrays"].set_index("array")
        names = [a for a in est.index if np.all(np.isfinite(est.loc[a, ["x_std", "y_std", "z_std"]].to_numpy(float)))]
        err = est.loc[names, list("xyz")].to_numpy(float) - truth.loc[names, list("xyz")].to_numpy(float)
        z_with.append((err / est.loc[names, ["x_std", "y_std", "z_std"]].to_numpy(float)).ravel())
    assert len(z_with) >= 10
    rms = lambda z: float(np.sqrt(np.mean(np.concatenate(z) ** 2)))
    assert 0.6 < rms(z_with) < 1.5


def test_velocity_sigma_follows_the_unmodelled_acceleration():
    """A trajectory with a known acceleration spectrum sampled every 3 s, exact velocities: the Hermite
    curve's velocity t* after each event misses the truth by about what ``velocity_sigma`` states (σ_odo
    tiny, so only the acceleration term counts)."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(2.5, 3.5, 60))
    freqs, amps, phases = rng.uniform(0.05, 0.3, (3, 4)), rng.uniform(0.1, 0.4, (3, 4)), rng.uniform(0, 6.3, (3, 4))

    def pos(q):
        return np.stack([np.sum(amps[a] / (2 * np.pi * freqs[a]) * np.sin(2 * np.pi * freqs[a] * q[:, None]
                                                                        + phases[a]), axis=1) for a in range(3)], 1)

    def vel(q):
        return np.stack([np.sum(amps[a] * np.cos(2 * np.pi * freqs[a] * q[:, None] + phases[a]), axis=1)
                         for a in range(3)], 1)

    t_star = 0.22
    sig = velocity_sigma(t, pos(t), vel(t), t_star, 1e-6)
    from calib.estimator.motion import sweep_middle
    err = sweep_middle(t, pos(t), vel(t), t_star)[1] - vel(t + t_star)
    ratio = float(np.sqrt(np.mean(err ** 2))) / sig
    assert 0.3 < ratio < 1.5
    assert velocity_sigma(t, pos(t), vel(t), 0.0, 1e-6) < 1e-5   # at the event itself: the velocity as given


def test_stationary_has_no_velocity_term():
    """A robot that stops for every chirp: no motion correction, so no velocity term (std as before)."""
    f, _ = simulate_features(2, 1e-4, 5.0, 0.01, seed=2)
    out = calibrate(f)
    assert "velocity_sigma_m_s" not in (out["report"]["stages"].get("motion") or {})


def _near_plane(seed, sigma_rho=1.5e-3, array="A3"):
    """A robot driving its speaker at 1 m ± 5 cm over a 6 × 6 m floor, array ``array`` planar (mics in meta)
    and level at that height (its mic plane through the sources: elevations of a few degrees, about half
    below the plane), its DOAs read as a planar array reads them: azimuth nearly exact, |elevation| from
    ρ = cos(el) + N(0, σ_ρ²) ≤ 1 (the stated hemisphere's side, as the frontend reports them).
    Returns (features, truth, the true elevations in degrees)."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(50 + seed)
    k = 30
    stops = np.column_stack([rng.uniform(0.5, 6.5, k), rng.uniform(0.5, 6.5, k), rng.uniform(0.9, 1.5, k)])
    stops = stops[np.argsort(np.arctan2(stops[:, 1] - 3.5, stops[:, 0] - 3.5))]    # a loop
    pos = np.array([[0, 0, 0], [7.0, 0.5, 2.5], [7.5, 7.0, 1.0], [0.3, 7.2, 2.2]], float)   # A3 level with the lowest sources
    f, tr = simulate_features(stops, 3e-5, 0.3, 0.01, seed=seed, positions=pos)
    a = tr["arrays"].set_index("array")
    R = Rotation.from_quat(a.loc[array, ["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
    s = tr["sources"][["x", "y", "z"]].to_numpy(float)
    w = R.inv().apply(s - a.loc[array, list("xyz")].to_numpy(float))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    n = R.inv().apply([0.0, 0.0, 1.0])                  # level: the mic plane horizontal
    e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    az = np.arctan2(w @ e2, w @ e1) + rng.normal(0.0, 2e-4, len(w))
    rho = np.minimum(np.sqrt(1.0 - (w @ n) ** 2) + rng.normal(0.0, sigma_rho, len(w)), 1.0)
    sin_el = np.sqrt(1.0 - rho ** 2)                    # ≥ 0: the stated hemisphere's side
    u = rho[:, None] * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2) + sin_el[:, None] * n
    doa = f["doa"].copy()
    m = (doa["array"] == array).to_numpy()
    doa.loc[m, ["ux", "uy", "uz"]] = u[doa.loc[m, "event"].to_numpy(int)]
    ring = 0.04 * np.array([[np.cos(t), np.sin(t), 0.0] for t in np.arange(6) * np.pi / 3])
    mics = ring @ np.vstack([e1, e2, n])               # a 6-mic circle in the plane ⟂ n
    meta = {**f["meta"], "mics": {array: mics.tolist()}}
    return f.replace(doa=doa, meta=meta), tr, np.degrees(np.arcsin(w @ n))


@pytest.mark.slow
def test_near_plane_rows_share_their_elevation_error(monkeypatch):
    """Planar array level with a robot's speaker (70 % of the sources within 3° of its mic plane, some below
    it), elevations rectified by ρ ≤ 1, sigmas estimated: its orientation error over seeds against its stated
    std. With the near-plane rows' shared error the std covers the error (error / std RMS < 1) and is wider
    than with those rows independent; on this scene it is conservative, not useless (the rectified bias here,
    ≈ 1.3°, is less than the 2.5-3.5° the rendered robot sessions show). With the array's pooled in-plane error
    it was 0.3 against 0.55 without; since each planar row carries its own leverage-corrected in-plane residual
    (h54o) the rectified rows' large residuals hold most of it themselves: 0.57 against 0.63."""
    import calib.estimator.uncertainty as U
    z_with, z_without = [], []
    for seed in range(8):
        g, tr, el = _near_plane(seed, sigma_rho=5e-4)
        assert np.mean(np.abs(el) < 3.0) > 0.3 and np.min(el) < 0 < np.max(el)   # the scene is what it says
        g = g.replace(meta={**g["meta"], "sigmas_estimated": ["sigma_doa_deg", "sigma_tdoa"]})
        rot = lambda o: np.degrees(np.linalg.norm(o["arrays"].set_index("array").loc[
            "A3", ["rx_std", "ry_std", "rz_std"]].to_numpy(float)))
        out = calibrate(g, **NO_TARGET)            # (its wide std would name it as short of the target)
        if "A3" in (out["report"]["verdict"].get("flagged_arrays") or []):
            continue                               # named: no std claimed
        e3 = next(p["geodesic_deg"] for p in evaluate(out, tr)["per_array"] if p["array"] == "A3")
        z_with.append(e3 / rot(out))
        monkeypatch.setattr(U, "FOLD_SIGMAS", 0.0)    # no row counts as near the plane
        z_without.append(e3 / rot(calibrate(g, **NO_TARGET)))
        monkeypatch.undo()
    rms = lambda z: float(np.sqrt(np.mean(np.square(z))))
    assert len(z_with) >= 5
    assert 0.15 < rms(z_with) < 1.0
    assert rms(z_without) > 1.05 * rms(z_with)
