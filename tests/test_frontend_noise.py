"""The sigmas the frontend claims (calib.frontend.noise) against independent truth: point sources with
analytic spherical wavefronts, synthetic clock tracks, and simulated rooms (claimed vs measured error)."""
from __future__ import annotations

import numpy as np
import pytest

from calib.frontend.noise import arrival_sd, near_field_fit, range_track
from calib.pipeline.features import session_features
from calib.pipeline.report.evaluate import feature_errors
from calib.pipeline.simulate import roomsim

C = 343.0
OCTAHEDRON = np.r_[np.eye(3), -np.eye(3)] * 0.05  # the hall preset's 10 cm arrays
CIRCLE_3D = np.c_[0.0354 * np.cos(np.arange(6) * np.pi / 3), 0.0354 * np.sin(np.arange(6) * np.pi / 3),
                  0.02 * (-1.0) ** np.arange(6)]


def spherical_residuals(mics, u, d, noise, rng):
    """Mic arrival times of a point source at range ``d`` along ``u`` (exact), referred to the origin with
    the plane wave (as the frontend does), minus their mean: (J, M), plus mic noise."""
    src = d[:, None] * u
    t = np.linalg.norm(src[:, None, :] - mics[None], axis=2) / C + (u @ mics.T) / C
    t += noise * rng.standard_normal(t.shape)
    return t - t.mean(axis=1, keepdims=True)


def random_directions(rng, n):
    u = rng.standard_normal((n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


@pytest.mark.parametrize("mics", [OCTAHEDRON, CIRCLE_3D])
def test_near_field_fit_recovers_the_curvature_and_the_mic_noise(mics):
    rng = np.random.default_rng(3)
    n_ev, noise = 400, 0.1e-6
    u, d = random_directions(rng, n_ev), rng.uniform(0.8, 4.0, n_ev)
    kappa, kappa_sd, s, qbar, n = near_field_fit(spherical_residuals(mics, u, d, noise, rng), u, mics, C)
    z = (kappa - 1 / d) / kappa_sd  # the second-order wavefront is the model: normalised errors ~ N(0, 1)
    ok = np.isfinite(z)
    assert ok.mean() > 0.95 and np.all(n == 6)
    assert abs(np.median(z[ok])) < 0.2 and 0.8 < 1.4826 * np.median(np.abs(z[ok])) < 1.25
    assert 0.85 < np.sqrt(np.mean(s[ok] ** 2)) / noise < 1.15  # the residual spread is the mic noise
    # the curvature is what the plane-wave spread mistook for noise
    plain = np.sqrt(np.sum(spherical_residuals(mics, u, d, noise, np.random.default_rng(3)) ** 2, axis=1) / 5)
    assert np.median(plain) > 2 * np.median(s)


def test_range_track_recovers_ranges_and_refuses_inconsistent_curvatures():
    rng = np.random.default_rng(5)
    j = 20
    e = np.sort(rng.uniform(0, 40, j))
    d = 2.5 + 1.5 * np.sin(e / 5)                    # the robot's range to the array (m)
    lag = d - (0.7 + 0.02 * e)                        # c × (arrival − a clock line with its own offset/slope)
    kappa_sd = np.full(j, 0.03)
    kappa = 1 / d + kappa_sd * rng.standard_normal(j)
    got = range_track(kappa, kappa_sd, lag, e)
    assert got is not None and np.max(np.abs(got - d)) < 0.15
    # curvatures unrelated to the track (scatter ≫ their errors): no range is claimed
    assert range_track(rng.permutation(kappa), kappa_sd, lag, e) is None
    # too few resolved curvatures: none either
    assert range_track(kappa, np.full(j, 1.0), lag, e) is None


def test_claimed_sd_covers_the_near_field_bias():
    # no mic noise, no reflections: each arrival's only error is the curvature bias of the mic mean, which
    # varies with the range; the claim must follow it (the per-array mean is a clock offset)
    rng = np.random.default_rng(7)
    j = 16
    e = np.arange(j) * 2.0
    d = 1.2 + 0.8 * np.cos(e / 6)
    u = random_directions(rng, j)
    src = d[:, None] * u
    t = np.linalg.norm(src[:, None, :] - OCTAHEDRON[None], axis=2) / C + (u @ OCTAHEDRON.T) / C
    t += 1e-9 * rng.standard_normal(t.shape)
    arrival = t.mean(axis=1)                          # = d / c + bias
    bias = arrival - d / C
    sd, info = arrival_sd(t - arrival[:, None], u, OCTAHEDRON, C, C * arrival - 0.3, e, np.ones(j, bool))
    assert info["range"] is not None and np.max(np.abs(info["range"] - d)) < 0.02
    measured = np.sqrt(np.mean((bias - bias.mean()) ** 2))
    assert 0.9 < np.sqrt(np.mean(sd**2)) / measured < 1.1


@pytest.mark.parametrize("mics,seed", [(OCTAHEDRON, 0), (OCTAHEDRON, 1), (CIRCLE_3D, 1)])
def test_claimed_sigma_tdoa_matches_the_measured_error(tmp_path, mics, seed):
    # a reverberant room (RT60 0.3 s, 30 dB): sigma_tdoa within 1.5× of the unflagged TDOA errors the
    # frontend made (TDOA-M less each array's mean, which the clock offset absorbs, and TDOA-S)
    sc = roomsim.make_scenario("paper-traj3", seed, rt60=0.3, snr=30.0, n_arrays=3, n_events=8, interval=1.0,
                               chirp={"duration": 0.25}, mics=mics.tolist())
    feats, _ = session_features(roomsim.simulate(sc, tmp_path / "rec"))
    e = feature_errors(feats, sc)
    keep_m = ~feats["tdoa_m"]["flag"].astype(bool).to_numpy()
    keep_s = ~feats["tdoa_s"]["flag"].astype(bool).to_numpy()
    dm, arr = e["tdoa_m"][keep_m].copy(), feats["tdoa_m"]["array"].to_numpy()[keep_m]
    for a in np.unique(arr):
        dm[arr == a] -= dm[arr == a].mean()
    claimed = feats["meta"]["sigma_tdoa"]
    for err in (dm, e["tdoa_s"][keep_s]):
        assert 1 / 1.5 < np.sqrt(np.mean(err**2)) / claimed < 1.5


@pytest.mark.parametrize("mics", [OCTAHEDRON, CIRCLE_3D])
def test_doa_spread_counts_the_mic_noise_not_the_wavefront_curvature(mics):
    """A near source's curvature is symmetric about the array and leaves the direction alone: the DOA sd
    claimed from the residuals is the one the mic noise alone gives (c σ √(tr P S⁺ P / 2)), not 2× more."""
    from calib.frontend.extract import doa_spread

    rng = np.random.default_rng(11)
    n_ev, noise = 400, 0.1e-6
    u, d = random_directions(rng, n_ev), rng.uniform(0.8, 2.0, n_ev)
    got = doa_spread(spherical_residuals(mics, u, d, noise, rng), u, mics, C)
    far = doa_spread(spherical_residuals(mics, u, np.full(n_ev, 1e6), noise, rng), u, mics, C)  # plane waves
    ratio = np.sqrt(np.mean(got**2) / np.mean(far**2))
    assert 0.85 < ratio < 1.15, ratio


def test_a_mic_left_out_of_the_fusion_does_not_inflate_the_claim():
    """One mic locked on a peak 50 µs late: the fusion leaves it out (its mask), and so does the claim."""
    from calib.frontend.timing import fuse_times

    rng = np.random.default_rng(2)
    n_ev, noise = 30, 0.2e-6
    u, d = random_directions(rng, n_ev), rng.uniform(1.0, 4.0, n_ev)
    t_org = spherical_residuals(OCTAHEDRON, u, d, noise, rng)
    t_org[::3, 4] += 50e-6
    arrival, _, fused = fuse_times(t_org)
    assert not fused[::3, 4].any() and fused[1::3].all()
    lag, e = np.full(n_ev, np.nan), np.arange(n_ev, dtype=float)
    kept, _ = arrival_sd(np.where(fused, t_org - arrival[:, None], np.nan), u, OCTAHEDRON, C, lag, e,
                         np.ones(n_ev, bool))
    every, _ = arrival_sd(t_org - arrival[:, None], u, OCTAHEDRON, C, lag, e, np.ones(n_ev, bool))
    assert np.sqrt(np.mean(kept**2)) < 2 * noise < np.sqrt(np.mean(every[::3] ** 2)) / 10


def test_an_array_of_absurd_doa_spreads_does_not_set_the_session_doa_sigma():
    """An occluded array whose DOA spreads are 1-2 rad (hard seed 9: 77-151°, unflagged) made the session's
    DOA sigma 35° and the estimator's 12°, so every DOA counted for nothing. Its rows, and a typical
    array's one row 100× its median, get the doubt "doa_spread"; the sigma is the RMS of the rest."""
    from calib.frontend.extract import DOA_SPREAD_FACTOR, flag_doa_spread, noise_estimates

    rng = np.random.default_rng(5)
    good = rng.uniform(0.004, 0.006, 20)
    good[7] = 100 * np.median(good)
    bad = rng.uniform(1.0, 2.0, 6)
    results = {name: {"has_doa": True, "doa_spread": sd, "flags": [[] for _ in sd],
                      "arrival_sd": np.full(len(sd), 1e-6), "spread": np.full(len(sd), 1e-6)}
               for name, sd in (("A1", good), ("A2", bad))}
    results["A1"]["flags"][3].append("doa_reflection")  # already doubtful: not in the median, not flagged again
    flag_doa_spread(results)
    flagged = {n: [k for k, f in enumerate(r["flags"]) if "doa_spread" in f] for n, r in results.items()}
    assert flagged == {"A1": [7], "A2": list(range(6))}
    assert DOA_SPREAD_FACTOR * np.median(np.delete(good, 3)) < good[7]
    typical = np.delete(good, [3, 7])
    want = np.degrees(np.sqrt(np.mean(typical**2)))
    assert noise_estimates(results)["sigma_doa_deg"] == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("n_late", [1, 2, 3, 4])
def test_mics_split_between_two_paths_fuse_on_the_earlier(n_late):
    """A reflection 1.3 pulse widths after the direct path, merged with it in the array's envelope: each mic's
    refined peak lands on one path or the other (lshape seed 10, A3: three of six mics 370 µs late; the median
    of the six was 188 µs late). The mics on the earliest path, at least two and a third of them, are fused;
    a single early mic (noise, a sidelobe) is no path; times that do not split are fused as before."""
    from calib.frontend.timing import fuse_times

    rng = np.random.default_rng(5)
    pulse, noise, m = 1 / 3500, 0.5e-6, 6
    t_org = rng.normal(0.0, noise, (20, m))
    late = np.stack([rng.permutation(m) < n_late for _ in range(20)])
    t_org[late] += 1.3 * pulse
    arrival, sd, fused = fuse_times(t_org, path_gap=0.5 * pulse)
    assert np.all(np.abs(arrival) < 5 * noise) and not fused[late].any()
    plain, _, _ = fuse_times(t_org)
    assert np.all(plain[late.sum(axis=1) * 2 >= m] > 100e-6) if n_late >= 3 else True   # the median's answer
    early = rng.normal(0.0, noise, (20, m))
    early[:, 0] -= 1.3 * pulse          # one mic early (no group of two): not taken for the direct path
    arrival, _, fused = fuse_times(early, path_gap=0.5 * pulse)
    assert np.all(np.abs(arrival) < 5 * noise) and not fused[:, 0].any()
    same, _, _ = fuse_times(t_org[~late.any(axis=1)], path_gap=0.5 * pulse)
    np.testing.assert_array_equal(same, fuse_times(t_org[~late.any(axis=1)])[0])
