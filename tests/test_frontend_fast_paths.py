"""Fast paths of the frontend against the straightforward computations they replace: the coarse-to-fine
DOA grid against the exhaustive grid (and its set-up: the caps and steering phasors against their
definitions), the timing's moments from grid samples (GridMoments) against its band sums and against the
true delay of a path; the event segments' band spectra taken a few events at a time against each segment's
own zero-padded FFT; the two-path refinement by linearity against subtracting the models; the onset search's
noise floors from one sort against np.median row by row; its sidelobe test for all events at once against the
event-by-event loop; the lag grid's folded weighting and magnitude against the product and np.abs."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.fft as sfft

import calib.frontend.timing as timing
from calib.frontend.timing import BandMoments, GridMoments, lag_grid, newton_envelope, newton_peak, spectra_setup
from calib.frontend.doa import _cap_indices, _grid_search, fibonacci_sphere, srp_setup, steering

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


def _chirp_envelope(n, rng):
    """An envelope like the matched filter's: noise, a reverberant chirp peak every ~2 s at 4.8 kHz, a stretch
    of digital silence (exact zeros: flat runs) and a clipped (flat-topped) peak."""
    env = np.abs(rng.standard_normal(n)).astype(np.float32)
    for c in np.arange(2000, n - 2000, 9600) + rng.integers(-500, 500, len(np.arange(2000, n - 2000, 9600))):
        k = np.arange(-300, 300)
        env[c + k] += (40.0 * np.exp(-np.abs(k) / 60.0) * (1 + 0.3 * np.cos(k / 3.0))).astype(np.float32)
    env[n // 3 : n // 3 + 20000] = 0.0
    env[n // 2 : n // 2 + 6] = 60.0
    return env


@pytest.mark.parametrize("seed, threshold, sep_s", [(0, 8.0, 0.25), (1, 3.0, 0.01), (2, 8.0, 1.0)])
def test_pick_peaks_equals_find_peaks_on_the_whole_envelope(seed, threshold, sep_s):
    """pick_peaks looks only around the samples above the threshold (bounded memory): the peaks and scores of
    find_peaks on the whole envelope with the per-sample floor as its height."""
    from scipy.signal import find_peaks

    from calib.frontend.detect import block_levels, local_floor_at, pick_peaks

    rng = np.random.default_rng(seed)
    env, rate = _chirp_envelope(400_000 + seed * 1234, rng), 4800.0
    block = int(0.25 * rate)
    floor = local_floor_at(block_levels(env, block), block, 0, len(env))
    want = find_peaks(env, height=threshold * floor, distance=max(1, int(sep_s * rate)))[0]
    idx, score = pick_peaks(env, rate, sep_s, threshold)
    assert len(want) > 10 and np.array_equal(idx, want)
    np.testing.assert_array_equal(score, env[want] / floor[want])


def test_detection_plot_labels_only_what_fits():
    """The detection plot draws an event's id only where it clears the last one drawn (a 2-hour session's
    thousands of ids per row would cost seconds to draw as an unreadable smear): sparse ids are all kept, crowded
    ones thinned to non-overlapping ones, each kept label at its own event's time."""
    from calib.frontend.diagnostics import FIG_WIDTH_IN, LABEL_CHAR_IN, MARGIN_IN, _legible

    s_per_in = 100.0 / (FIG_WIDTH_IN - MARGIN_IN["left"] - MARGIN_IN["right"])
    sparse = np.arange(0.0, 100.0, 5.0)
    assert [t for t, _ in _legible(sparse, [str(k) for k in range(len(sparse))], 100.0)] == list(sparse)
    dense = np.sort(np.random.default_rng(0).uniform(0, 100, 400))
    labels = [str(1000 + k) for k in range(len(dense))]
    kept = _legible(dense, labels, 100.0)
    assert 10 < len(kept) < len(dense) and kept[0] == (dense[0], labels[0])
    assert all(labels[int(np.flatnonzero(dense == t)[0])] == lab for t, lab in kept)
    half = 0.5 * 4 * LABEL_CHAR_IN * s_per_in   # 4-character labels
    assert np.all(np.diff([t for t, _ in kept]) >= 2 * half)


@pytest.mark.parametrize("fs_from, fs_to", [(16000, 44100), (16000, 48000), (48000, 16000), (44100, 48000)])
def test_reference_chirp_resampled_to_the_sweep_at_the_new_rate(fs_from, fs_to):
    """A reference chirp recorded at another rate than an array's (mixed boards) is resampled band-limited:
    the sweep sampled at the new rate directly (independent truth), to 1e-4 of its amplitude (scipy.signal's
    polyphase filter, used before: 2e-3), ceil(N fs_to / fs_from) samples."""
    from calib.frontend.signals import resample, sweep

    ref = sweep(np.arange(8000 * fs_from // 16000) / fs_from, 500.0, 4000.0, 0.5, 0.005)
    out = resample(ref, fs_from, fs_to)
    assert len(out) == -(-len(ref) * fs_to // fs_from)
    truth = sweep(np.arange(len(out)) / fs_to, 500.0, 4000.0, 0.5, 0.005)
    assert np.max(np.abs(out - truth)) < 1e-4


def test_fourier_resample_is_scipys():
    """fourier_resample (the drift bias's and the Doppler bank's stretching) gives scipy.signal.resample's values."""
    from scipy.signal import resample

    from calib.frontend.signals import fourier_resample

    x = np.random.default_rng(3).standard_normal(101)
    for num in (99, 100, 101, 103, 202, 50):
        np.testing.assert_allclose(fourier_resample(x, num), resample(x, num), rtol=0, atol=1e-12)


def test_shared_setup_is_one_per_board_kind_and_keeps_few_doppler_banks():
    """Arrays with the same template, rate, band and segment length share one spectra setup (its cached pulses
    and banks computed once); a setup outlives its session, so it keeps only the last KEPT_BANKS Doppler banks,
    each equal to one built on a fresh setup."""
    from calib.frontend.signals import chirp_band, sweep
    from calib.frontend.timing import KEPT_BANKS, shared_setup, spectra_setup, stretch_bank

    fs = 16000
    tmpl = sweep(np.arange(8000) / fs, 500.0, 4000.0, 0.5, 0.005)
    band = chirp_band({"f0": 500.0, "f1": 4000.0}, tmpl, fs)
    a, b = shared_setup(tmpl, fs, band, 9000), shared_setup(tmpl.copy(), fs, band, 9000)
    assert a is b and shared_setup(tmpl, fs, band, 9001) is not a
    for k in range(KEPT_BANKS + 3):
        eps = np.linspace(-1e-3, 1e-3, 5 + k)
        got = stretch_bank(tmpl, a, eps)
        want = stretch_bank(tmpl, spectra_setup(tmpl, fs, band, 9000), eps)
        np.testing.assert_array_equal(got[0], want[0])
        assert len(a["_stretch_banks"]) <= KEPT_BANKS


@pytest.mark.parametrize("fs", [16000, 48000])
def test_stretched_spectra_equal_the_resampled_templates_transform(fs):
    """The Doppler bank's stretched spectra (a chirp z-transform at the stretched bins) against their definition:
    the template zero-padded to ``pad``, band-limited resampled to ``pad + k`` samples (stretched by 1 + k / pad)
    and transformed at the segment's FFT size, for stretches either side of 0 (a 0.5 s sweep, with fades)."""
    from calib.frontend.signals import chirp_band, fourier_resample, sweep

    tmpl = sweep(np.arange(fs // 2) / fs, 500.0, 4000.0, 0.5, 0.005)
    band = chirp_band({"f0": 500.0, "f1": 4000.0}, tmpl, fs)
    setup = spectra_setup(tmpl, fs, band, len(tmpl) + fs // 20)
    nfft, kb = setup["nfft"], setup["kb"]
    pad, ks = sfft.next_fast_len(2 * len(tmpl)), (-37, -1, 0, 2, 53)
    got = timing._stretched_spectra(tmpl.tobytes(), nfft, int(kb[0]), len(kb), pad, ks)
    buf = np.r_[tmpl, np.zeros(pad - len(tmpl))]
    want = np.array([sfft.rfft(fourier_resample(buf, pad + k)[:pad][:nfft], nfft)[kb] for k in ks])
    assert np.max(np.abs(got - want)) < 1e-8 * np.max(np.abs(want))


def test_cubic_interpolation_of_the_oversampled_template_is_band_limited_exact():
    """_cubic_at on a 16× oversampled band-limited periodic signal (two tones at the top of a 4 kHz band at
    16 kHz, sampled at 256 kHz) against the tones' exact values at arbitrary instants: ~1e-6 of the amplitude."""
    rate, n = 256000, 25600
    f = np.array([3990.0, 2510.0])
    y = np.sum(np.cos(2 * np.pi * f[:, None] * np.arange(n) / rate), axis=0)
    t = np.random.default_rng(5).uniform(0, n / rate, 500)
    exact = np.sum(np.cos(2 * np.pi * f[:, None] * t), axis=0)
    assert np.max(np.abs(timing._cubic_at(y, t * rate) - exact)) < 1e-5


def test_segment_band_spectra_in_batches_equal_each_segments_own_fft(monkeypatch):
    # segments before, across either end of, inside and after the recording; batches of 3 events (8 in all)
    rng = np.random.default_rng(5)
    x = rng.standard_normal((3, 5000)).astype(np.float32)
    setup = spectra_setup(rng.standard_normal(400), 16000, (500, 4000), 1000)
    starts = np.array([-2000, -300, 0, 2000, 4500, 4999, 5000, 9000])
    monkeypatch.setattr(timing, "SEGMENT_BATCH_BYTES", 3 * 4 * 3 * setup["nfft"])
    got = timing._band_spectra(x, starts, setup, workers=1)
    for s0, g in zip(starts, got):
        seg = np.zeros((3, setup["nfft"]), np.float32)
        a, b = max(s0, 0), min(s0 + setup["seg_len"], x.shape[1])
        if b > a:
            seg[:, a - s0 : b - s0] = x[:, a:b]
        np.testing.assert_array_equal(g, sfft.rfft(seg, axis=-1)[:, setup["kb"]])


@pytest.mark.parametrize("fs, band", [(48000, (500, 10000)), (16000, (500, 6000))])
def test_two_path_refinement_by_linearity_equals_subtracting_the_models(fs, band):
    """refine_two_paths evaluates each path's moments with the other's model subtracted by linearity (the
    spectra's lag-grid moments less the pulse's), never forming ``c − path_model``: the same times and
    amplitudes as the straightforward alternation, and on two clean overlapping paths their true delays."""
    rng = np.random.default_rng(11)
    setup, _, _, _ = _paths_setup(fs, band, rng, n_paths=1)
    shape = setup["weights"] * np.abs(setup["tmpl_conj"]) ** 2
    pulse = fs / (band[1] - band[0])
    t1 = rng.uniform(250, 300, (4, 3)) / fs
    t2 = t1 + rng.uniform(1.5, 3.5, t1.shape) * pulse / fs
    a1 = np.exp(1j * rng.uniform(0, 2 * np.pi, t1.shape))
    a2 = rng.uniform(0.3, 0.8, t1.shape) * np.exp(1j * rng.uniform(0, 2 * np.pi, t1.shape))
    c = (timing.path_model(setup, shape, t1, a1) + timing.path_model(setup, shape, t2, a2)).astype(np.complex64)
    # a grid fit's starting values: off by a fraction of a sample, amplitudes off by 10 %
    start = (t1 + rng.uniform(-0.3, 0.3, t1.shape) / fs, 0.9 * a1, t2 + rng.uniform(-0.3, 0.3, t1.shape) / fs, 0.9 * a2)
    freqs = setup["freqs"]
    w1, b1, w2, b2 = start
    for _ in range(3):
        w2, b2 = newton_envelope(c - timing.path_model(setup, shape, w1, b1, c.dtype), freqs, w2, iters=1)
        w1, b1 = newton_envelope(c - timing.path_model(setup, shape, w2, b2, c.dtype), freqs, w1, iters=1)
    got = timing.refine_two_paths(c, setup, shape, *start)
    for x, want in zip(got, (w1, b1, w2, b2)):
        # single precision: the lag grid's samples round at ~1e-6 of the peak (3e-6 samples, 6e-11 s at 48 kHz)
        assert np.max(np.abs(x - want)) * (fs if np.isrealobj(want) else 1.0) < 1e-5
    # towards the truth: three alternations from starts up to 0.3 samples off end within 0.1 samples
    assert np.max(np.abs(got[0] - t1)) < 0.1 / fs and np.max(np.abs(got[2] - t2)) < 0.1 / fs


def test_prefix_medians_equal_numpy_medians_row_by_row():
    """direct_path_lag's noise floors from one sort of all rows: each row's median before its peak (or of the
    whole row when fewer than 16 samples precede it), exactly np.median's values, odd and even lengths and
    ties included; a non-finite row falls back to np.median's semantics."""
    rng = np.random.default_rng(12)
    env = np.abs(rng.standard_normal((40, 300))).astype(np.float32)
    env[5, :50] = 0.25                                   # ties
    kmax = rng.integers(0, 300, 40)
    kmax[:4] = [0, 15, 16, 17]                            # short prefixes: the whole row
    want = [np.median(e[:k] if k >= 16 else e) for e, k in zip(env, kmax)]
    np.testing.assert_array_equal(timing._prefix_medians(env, kmax), want)
    env[7, 3] = np.nan
    got = timing._prefix_medians(env, kmax)
    assert np.isnan(got[7]) == np.isnan(np.median(env[7, : kmax[7]] if kmax[7] >= 16 else env[7]))
    np.testing.assert_array_equal(np.delete(got, 7), np.delete(want, 7))


@pytest.mark.parametrize("near", [False, True])
def test_onset_choice_for_all_events_at_once_equals_the_event_by_event_loop(near):
    """direct_path_lag's choice among its candidates (the earliest peak that no later, stronger peak's sidelobes
    explain) and its "shadowed" flag, all rows advancing together, equal the loop over events and candidates on
    envelopes of a few paths with sidelobes, noise and ties: the rows cover a direct path kept, one rejected as
    a sidelobe, and none before the strongest peak."""
    rng = np.random.default_rng(5)
    fs, band = 16000, (500.0, 4000.0)
    t = np.arange(800) / fs
    setup = spectra_setup(np.sin(2 * np.pi * (500 * t + 3500 / 0.1 * t * t)), fs, band, 4000)   # a 50 ms sweep
    n = 600
    pulse, near_p = timing.pulse_envelope(setup, n, plain=True), timing.pulse_near(setup, n, 2, plain=True)
    lags = np.arange(n)
    env = np.zeros((80, n), np.float32)
    for row in env:
        # a strong path, an earlier one near the level of its sidelobes there (0.5-4x), and others at random
        k2, d = rng.integers(300, 550), rng.integers(2, 60)
        paths = [(k2, 1.0), (k2 - d, rng.uniform(0.5, 4.0) * pulse[d])]
        paths += list(zip(rng.integers(50, 550, rng.integers(0, 4)), rng.uniform(0.02, 1.0, 4)))
        for k, a in paths:
            row += (a * np.interp(np.abs(lags - k), np.arange(n), pulse)).astype(np.float32)
        row += np.abs(rng.normal(0, 0.003, n)).astype(np.float32)
    env[3, 100:110] = env[3, 100]                          # a plateau (ties)
    got = timing.direct_path_lag(env, pulse, 6.0, 0.05, 2.0, near=near_p if near else None)
    orig = timing._first_onsets
    try:
        timing._first_onsets = first_onsets_loop
        want = timing.direct_path_lag(env, pulse, 6.0, 0.05, 2.0, near=near_p if near else None)
    finally:
        timing._first_onsets = orig
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    kmax = np.argmax(env, axis=1)
    assert np.any(got[0] < kmax) and np.any(got[0] == kmax) and np.any(got[3])   # each case occurs


def first_onsets_loop(env, above, kmax, pulse_env, sidelobe_margin, near):
    """timing._first_onsets row by row, candidate by candidate (the plain formula; tests compare the two)."""
    out, shadowed = kmax.copy(), np.zeros(len(kmax), bool)
    n_pulse = len(pulse_env)
    for i in range(len(kmax)):
        cand = np.flatnonzero(above[i])
        strong = np.append(cand, kmax[i])  # candidates and the maximum, earliest first
        for k in cand:
            later = strong[(strong > k) & (env[i, strong] > env[i, k])]
            d = np.minimum(later - k, n_pulse - 1)
            if later.size and env[i, k] <= sidelobe_margin * np.sum(env[i, later] * pulse_env[d]):
                dn = np.minimum(later - k, len(near) - 1) if near is not None else None
                if near is None or env[i, k] > timing.SHADOW_MARGIN * np.max(env[i, later] * near[dn]):
                    shadowed[i] = True
                continue  # may be a later, stronger peak's sidelobe
            out[i] = k
            break
    return out, shadowed


def test_lag_grid_weighting_and_magnitude_equal_the_product_and_abs():
    """lag_grid(c, factor=f, magnitude=True) is np.abs(lag_grid(c * f)) bit for bit (the Doppler search's
    envelopes), and magnitude=True alone np.abs(lag_grid(c))."""
    rng = np.random.default_rng(8)
    fs = 16000
    setup = spectra_setup(np.sin(2 * np.pi * 1000 * np.arange(800) / fs), fs, (500.0, 4000.0), 4000)
    fb = len(setup["kb"])
    c = (rng.standard_normal((5, 3, fb)) + 1j * rng.standard_normal((5, 3, fb))).astype(np.complex64)
    f = np.exp(1j * rng.uniform(0, 2 * np.pi, fb)).astype(np.complex64)
    np.testing.assert_array_equal(lag_grid(c, setup, 100, 900, factor=f, magnitude=True),
                                  np.abs(lag_grid(c * f, setup, 100, 900)))
    np.testing.assert_array_equal(lag_grid(c, setup, 100, 900, magnitude=True), np.abs(lag_grid(c, setup, 100, 900)))
