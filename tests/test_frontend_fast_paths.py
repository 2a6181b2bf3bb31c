"""Fast paths of the frontend against the straightforward computations they replace: the coarse-to-fine
DOA grid against the exhaustive grid (and its set-up: the caps and steering phasors against their
definitions), the one-selection median against ``np.median``, the detection's
peak search around the above-threshold stretches against ``scipy.signal.find_peaks`` on the whole
envelope (and its own local maxima and distance rule, which replace scipy.signal's), the FFT resampling
against ``scipy.signal.resample``, the 16-bit channel sum (a float32 matrix-vector product) against float32
accumulation, the timing's moments from grid samples (GridMoments) against its band sums and against the
true delay of a path."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.signal as ss

from calib.frontend.detect import _peaks_above, local_floor, local_maxima, median_last, select_by_distance
from calib.frontend.timing import (BandMoments, GridMoments, cis_powers, cis_tables, fft_resample, lag_grid,
                                   newton_envelope, newton_peak, spectra_setup)
from calib.frontend.doa import _cap_indices, _grid_search, fibonacci_sphere, srp_setup, steering
from calib.frontend.signals import SUM_BLOCK_FRAMES, _int_channel_sum

C = 343.0
MICS_3D = np.c_[0.0354 * np.cos(np.arange(6) * np.pi / 3), 0.0354 * np.sin(np.arange(6) * np.pi / 3),
                0.02 * (-1.0) ** np.arange(6)]


@pytest.mark.parametrize("planar", [False, True])
def test_coarse_to_fine_grid_finds_the_exhaustive_grid_point(planar):
    # noisy, reverberant-looking gated spectra: a plane wave plus a weaker second one and noise
    rng = np.random.default_rng(3)
    mics = MICS_3D * [1, 1, 0] if planar else MICS_3D
    freqs = np.linspace(500, 4000, 57)
    u1, u2 = fibonacci_sphere(200), fibonacci_sphere(200)[rng.permutation(200)]
    g = (np.exp(2j * np.pi * freqs * (u1 @ mics.T)[..., None] / C)
         + 0.5 * np.exp(2j * np.pi * freqs * (u2 @ mics.T)[..., None] / C)
         + 0.3 * (rng.standard_normal((200, 6, 57)) + 1j * rng.standard_normal((200, 6, 57))))
    g /= np.abs(g)
    setup = srp_setup(mics, freqs, C, 3.0)
    fidx, w = setup["fidx"], np.ones(len(freqs))
    gt = np.transpose(g[:, :, fidx], (2, 1, 0)).astype(np.complex64)
    p = sum(w[fidx[f]] * np.abs(setup["steer"][f] @ gt[f]) ** 2 for f in range(len(fidx)))
    exhaustive = np.argmax(p, axis=0)
    fast = _grid_search(gt, setup, w, fidx)
    same = fast == exhaustive
    # where they differ, only by a tie at float32 rounding (planar: the mirror images' powers)
    np.testing.assert_allclose(p[fast, np.arange(200)][~same], p[exhaustive, np.arange(200)][~same], rtol=1e-5)
    assert same.mean() > 0.95


@pytest.mark.parametrize("step_deg, hemisphere", [(3.0, None), (2.0, (0.0, 0.6, 0.8)), (5.0, (0.0, 0.0, -1.0))])
def test_cap_indices_and_steering_match_their_definitions(step_deg, hemisphere):
    step = np.deg2rad(step_deg)
    grid, coarse = fibonacci_sphere(int(4 * np.pi / step**2)), fibonacci_sphere(int(4 * np.pi / (3 * step) ** 2))
    if hemisphere is not None:
        grid, coarse = grid[grid @ hemisphere >= -0.5 * step], coarse[coarse @ hemisphere >= -0.5 * 3 * step]
    cos_max = np.cos(6 * step)
    cap = _cap_indices(coarse, grid, cos_max)
    near = coarse @ grid.T >= cos_max  # each row: its grid points ascending, then the last repeated
    for row, want in zip(cap, near):
        idx = np.flatnonzero(want)
        assert np.array_equal(row[: len(idx)], idx) and np.all(row[len(idx):] == idx[-1])
    assert cap.shape[1] == near.sum(axis=1).max()
    freqs = np.linspace(500.0, 10000.0, 16)
    want = np.exp(-2j * np.pi * freqs[:, None, None] * (grid @ MICS_3D.T)[None] / C)
    got = steering(grid, MICS_3D, freqs, C)
    assert got.dtype == np.complex64 and got.shape == want.shape
    assert np.max(np.abs(got - want)) < 2e-6  # float32 phases of a few radians: rounding only


def test_median_last_equals_numpy_median():
    rng = np.random.default_rng(0)
    for shape in [(1,), (2,), (7,), (1000,), (5, 8), (3, 4, 9), (40, 3000)]:
        for dtype in (np.float32, np.float64):
            a = rng.standard_normal(shape).astype(dtype)
            got, want = median_last(a), np.median(a, axis=-1)
            assert got.dtype == want.dtype and np.array_equal(got, want)


def test_median_last_long_arrays_bracketed():
    """Long 1-D arrays take the bracketed selection: still numpy's median exactly, with ties, digital
    silence (a constant majority) and heavy tails, odd and even lengths."""
    rng = np.random.default_rng(3)
    for trial in range(40):
        n = int(rng.integers(1 << 15, 1 << 17)) + trial % 2
        a = rng.standard_normal(n)
        if trial % 4 == 1:
            a = np.abs(a) ** 3
        if trial % 4 == 2:
            a = np.round(a * 3) / 3
        if trial % 4 == 3:
            a[: n // 2 + int(rng.integers(-50, 50))] = 0.0
        a = a.astype(np.float32 if trial % 3 else np.float64)
        got, want = median_last(a), np.median(a)
        assert np.asarray(got).dtype == np.asarray(want).dtype and got == want


def test_peaks_above_equals_find_peaks():
    rng = np.random.default_rng(1)
    for trial in range(400):
        n = int(rng.integers(5, 3000))
        env = np.abs(rng.standard_normal(n)).astype(np.float32)
        if trial % 3 == 0:
            env = np.round(env * 4).astype(np.float32) / 4  # plateaus
        if trial % 5 == 0:
            env[: int(rng.integers(0, n))] = 0  # digital silence
        for k in rng.integers(0, n, int(rng.integers(0, 6))):
            env[k : k + int(rng.integers(1, 30))] += rng.uniform(1, 20)
        height = rng.uniform(0, 3) * (1 + (np.arange(n) // int(rng.integers(5, 400))) % 3)
        if trial % 7 == 0:
            height = np.zeros(n)
        d = int(rng.integers(1, 200))
        np.testing.assert_array_equal(_peaks_above(env, height, d), ss.find_peaks(env, height=height, distance=d)[0])


def test_local_maxima_and_distance_rule_equal_find_peaks_with_plateaus_and_ties():
    # few distinct levels: plateaus at the ends and inside, equal peak heights (the distance rule's ties)
    rng = np.random.default_rng(4)
    for trial in range(2000):
        x = rng.integers(0, int(rng.integers(1, 6)), int(rng.integers(0, 60))).astype(np.float32)
        d = float(rng.uniform(1, 9)) if trial % 2 else int(rng.integers(1, 9))
        peaks = local_maxima(x)
        np.testing.assert_array_equal(peaks, ss.find_peaks(x)[0])
        np.testing.assert_array_equal(peaks[select_by_distance(peaks, x[peaks].astype(float), d)],
                                      ss.find_peaks(x, distance=d)[0])


@pytest.mark.parametrize("n,num", [(100, 130), (100, 70), (101, 130), (101, 70), (100, 101), (4096, 4097),
                                   (4097, 4095), (64, 64), (1, 3)])
def test_fft_resample_equals_scipy_resample(n, num):
    x = np.random.default_rng(n + num).standard_normal(n)
    np.testing.assert_allclose(fft_resample(x, num), ss.resample(x, num), rtol=0, atol=1e-13)


@pytest.mark.parametrize("dtype,m", [(np.int16, 6), (np.int16, 1), (np.int16, 256), (np.int32, 4)])
def test_int_channel_sum_equals_float_accumulation(dtype, m):
    rng = np.random.default_rng(2)
    info = np.iinfo(dtype)
    n = 2 * SUM_BLOCK_FRAMES + 123 if m <= 6 else 2000  # several blocks and a partial one
    f = rng.integers(info.min, info.max, (n, m), dtype=dtype)
    f[0], f[-1] = info.min, info.max
    want = f[:, 0].astype(np.float32)
    for ch in range(1, m):
        want += f[:, ch]
    got = _int_channel_sum(f)
    assert got.dtype == np.float32 and np.array_equal(got, want)
    scaled = np.full(n + 2, np.nan, np.float32)
    _int_channel_sum(f, 2.0**-15, out=scaled[1:-1])  # the full scale folded in: still exact
    assert np.array_equal(scaled[1:-1], want * np.float32(2.0**-15)) and np.all(np.isnan(scaled[[0, -1]]))


def test_cis_powers_equal_direct_exponentials():
    """The phasor tables by repeated multiplication agree with direct complex exponentials to ~1e-12 for
    lags up to 0.6 s and 80 steps (timing errors of ~1e-17 s), for many lags and for few (direct path)."""
    rng = np.random.default_rng(4)
    for shape in [(3,), (14, 6), (40, 9, 6)]:
        tau = rng.uniform(-0.6, 0.6, shape)
        for f0, df, n in [(0.0, 1.6, 80), (500.0, 125.0, 76), (37.5, 93.75, 10)]:
            want = np.exp(2j * np.pi * tau[..., None] * (f0 + df * np.arange(n)))
            got = cis_powers(tau, f0, df, n)
            assert got.shape == want.shape and np.max(np.abs(got - want)) < 1e-11


def test_cis_tables_equal_two_cis_powers():
    """The inner and outer tables stepped in one loop are the two separate tables, layout for layout and
    value for value up to rounding (bit for bit with numpy 2; numpy 1.26 rounds a strided complex multiply
    differently, ~1e-15), above and below the loop's lag count."""
    rng = np.random.default_rng(5)
    for shape in [(3,), (14, 6), (2, 40, 6)]:
        tau = rng.uniform(-0.6, 0.6, shape)
        for f0, df, b, n_a in [(500.0, 1.6, 76, 76), (37.5, 2.5, 9, 7), (120.0, 0.8, 1, 1)]:
            inner, outer = cis_tables(tau, f0, df, b, n_a)
            want_in, want_out = cis_powers(tau, 0.0, df, b), cis_powers(tau, f0, df * b, n_a)
            for got, want in ((inner, want_in), (outer, want_out)):
                assert got.strides == want.strides and np.max(np.abs(got - want)) < 1e-14


def test_local_floor_blockwise():
    """local_floor, written block by block, against its definition sample by sample: the max of the
    block medians of a sample's block and its neighbours (a partial last block takes the last full
    block's median) and of the global median."""
    rng = np.random.default_rng(5)
    for n, block in [(10007, 1000), (9000, 1000), (500, 1000), (1, 3)]:
        env = np.abs(rng.standard_normal(n)).astype(np.float32)
        nb = max(1, n // block)
        med = [np.median(env[b * block:(b + 1) * block]) for b in range(nb)] if n >= block else [np.median(env)]
        if n >= block and nb * block < n:
            med.append(med[-1])
        want = np.array([max(max(med[max(b - 1, 0)], med[b], med[min(b + 1, len(med) - 1)]), np.median(env))
                         for b in np.minimum(np.arange(n) // block, len(med) - 1)], np.float32)
        np.testing.assert_array_equal(local_floor(env, block), want)


def test_setup_cache_computes_a_shared_key_once_across_threads():
    import threading
    import time

    from calib.memo import SetupCache

    cache, calls = SetupCache(4), []

    def make():
        calls.append(threading.get_ident())
        time.sleep(0.2)  # long enough for the other thread to ask meanwhile
        return object()

    got = [None, None]
    threads = [threading.Thread(target=lambda k=k: got.__setitem__(k, cache.get("key", make))) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and got[0] is got[1]

    def fails():  # a failed computation is not cached, and a waiting thread then computes the value itself
        calls.append("fail")
        time.sleep(0.2)
        raise RuntimeError("boom")

    errors, values = [], []
    first = threading.Thread(target=lambda: errors.append(pytest.raises(RuntimeError, cache.get, "other", fails)))
    first.start()
    time.sleep(0.05)
    values.append(cache.get("other", lambda: "made"))
    first.join()
    assert len(errors) == 1 and values == ["made"] and calls.count("fail") == 1


def _paths_setup(fs, band, rng, n_paths=5, shape=(3, 4)):
    """A chirp's spectra set-up at ``fs`` and whitened-like spectra of a few paths with random delays
    (200–400 samples) and gains: c_f = Σ_p a_p w_f e^{−j2πf t_p}, complex64 as the frontend's."""
    n = int(0.2 * fs)
    t = np.arange(n) / fs
    template = np.sin(2 * np.pi * (band[0] * t + (band[1] - band[0]) / 0.4 * t * t))
    setup = spectra_setup(template, fs, band, n + 3000)
    f, w = setup["freqs"], setup["weights"]
    delays = rng.uniform(200, 400, shape + (n_paths,)) / fs
    gains = rng.normal(size=shape + (n_paths,))
    c = np.einsum("...p,...pf->...f", gains, w * np.exp(-2j * np.pi * f * delays[..., None]))
    return setup, (c / np.abs(c).max()).astype(np.complex64), delays, gains


@pytest.mark.parametrize("fs, band", [(48000, (500, 10000)), (16000, (500, 6000)), (16000, (200, 7600)),
                                      (44100, (300, 16000))])
def test_grid_moments_equal_band_moments(fs, band):
    """The kernel's value, slope and curvature from the lag grid's samples equal the band sums over all
    bins, to single precision, at lags between the samples, for narrow and wide bands (small margins)."""
    rng = np.random.default_rng(6)
    setup, c, _, _ = _paths_setup(fs, band, rng)
    lo, hi = 100, 600
    grid = GridMoments(lag_grid(c, setup, lo, hi), lo, setup)
    tau = rng.uniform(250, 350, c.shape[:-1]) / fs
    assert grid.covers(tau) and not grid.covers(np.full(c.shape[:-1], (lo + 3) / fs))
    got, want = grid(tau), BandMoments(c, setup["freqs"])(tau)
    for k in range(3):
        assert np.max(np.abs(got[k] - want[k])) < 1e-5 * np.max(np.abs(want[k]))
    assert np.allclose(grid(tau, orders=1)[0], got[0])


def test_newton_from_grid_samples_finds_a_single_path_delay():
    """One path per mic at a known sub-sample delay: the envelope and carrier peaks refined from the lag
    grid's samples are the path's delay (to ~1e-10 s), as with the band sums."""
    rng = np.random.default_rng(7)
    fs = 48000
    setup, c, delays, _ = _paths_setup(fs, (500, 10000), rng, n_paths=1)
    lo = 100
    r = lag_grid(c, setup, lo, 600)
    grid = GridMoments(r, lo, setup)
    start = (np.argmax(np.abs(r), axis=-1) + lo) / fs  # the nearest grid lag
    truth = delays[..., 0]  # r(τ) = Σ c_f e^{j2πfτ} = a Σ w_f e^{j2πf(τ − t_p)} peaks at τ = t_p
    for sums in (grid, None):
        env_tau, z = newton_envelope(c, setup["freqs"], start, iters=3, sums=sums)
        tau, _ = newton_peak(c, setup["freqs"], env_tau, np.angle(z), iters=3, sums=sums)
        assert np.max(np.abs(env_tau - truth)) < 1e-9 and np.max(np.abs(tau - truth)) < 1e-9
