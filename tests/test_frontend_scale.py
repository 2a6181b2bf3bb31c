"""The frontend at scale: association in O(K log K), audio read in bounded memory (issue 12)."""
from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest
import soundfile as sf

from calib.errors import InputError
from calib.frontend.associate import associate
from calib.frontend.detect import matched_envelope
from calib.frontend.signals import ArrayAudio, sweep

from .sessions import read_array_audio


def clock_scene(k, seed, miss=0.05, n_spurious=None, periodic=False, jitter=0.03):
    """Detections of ``k`` events on a clock with offset and drift: arrivals with propagation jitter, some
    events lost, spurious detections at least 0.3 s from any arrival, shuffled. Returns det, score,
    t_emit, truth (event of each detection or -1), drift."""
    rng = np.random.default_rng(seed)
    gaps = np.full(k - 1, 2.0) if periodic else rng.uniform(1.5, 3.5, k - 1)
    t_emit = np.cumsum(np.r_[rng.uniform(0, 5), gaps])
    drift, offset = rng.uniform(-1e-3, 1e-3), rng.uniform(-20, 20)
    arr = offset + (1 + drift) * (t_emit - t_emit[0] + rng.uniform(0, jitter, k))
    keep = rng.random(k) > miss
    n_sp = int(0.1 * k) if n_spurious is None else n_spurious
    spur = rng.uniform(arr.min() - 2, arr.max() + 2, n_sp)
    p = np.clip(np.searchsorted(arr, spur), 1, k - 1)
    spur = spur[np.minimum(np.abs(spur - arr[p - 1]), np.abs(spur - arr[p])) > 0.3]
    det = np.r_[arr[keep], spur]
    score = np.r_[rng.uniform(20, 100, keep.sum()), rng.uniform(10, 200, len(spur))]
    perm = rng.permutation(len(det))
    truth = np.r_[np.flatnonzero(keep), np.full(len(spur), -1)][perm]
    return det[perm], score[perm], t_emit, truth, drift


def cpu_seconds(fn, *args):
    t0 = time.process_time()
    out = fn(*args)
    return time.process_time() - t0, out


def test_association_of_2000_events_is_fast_and_exact():
    # 2000 events (a robot chirping for over an hour), 5 % lost, 200 spurious detections, drift up to 1e-3
    det, score, t_emit, truth, drift = clock_scene(2000, seed=3)
    cpu, res = cpu_seconds(associate, det, score, t_emit)
    np.testing.assert_array_equal(res["event_of"], truth)
    assert set(np.flatnonzero(res["det_of"] < 0)) == set(range(2000)) - set(truth[truth >= 0])
    assert abs(res["scale"] - 1 - drift) < 1e-6 and not res["ambiguous"]
    assert cpu < 1.0, f"{cpu:.2f} s of CPU for 2000 events"


def test_association_time_grows_near_linearly():
    # the exhaustive search grew like K⁴: 4× the events took ~256× as long. Near-linear: well under 16×
    cost = {}
    for k in (1000, 4000):
        det, score, t_emit, truth, _ = clock_scene(k, seed=k)
        cost[k], res = cpu_seconds(associate, det, score, t_emit)
        np.testing.assert_array_equal(res["event_of"], truth)
    assert cost[4000] < 10 * max(cost[1000], 0.01), cost


@pytest.mark.parametrize("seed", range(3))
def test_long_periodic_schedule_missing_its_first_event_is_flagged(seed):
    # 400 chirps exactly 2 s apart, the first one lost: "events 1..399" and "events 0..398" fit equally
    # well. The window and growth stages see only local patterns; the global offset scan must find both
    t_emit = np.arange(400) * 2.0
    rng = np.random.default_rng(seed)
    det = 7.3 + 1.00005 * (t_emit[1:] + rng.uniform(0, 0.02, 399))
    res = associate(det, np.ones(399), t_emit)
    assert res["ambiguous"] and res["n_matched"] == 399
    # with the robot's usual irregular log the same detections are unambiguous and all right
    t_emit = np.cumsum(np.r_[0.0, 2.0 + rng.uniform(-0.3, 0.3, 399)])
    det = 7.3 + 1.00005 * (t_emit[1:] + rng.uniform(0, 0.02, 399))
    res = associate(det, np.ones(399), t_emit)
    assert not res["ambiguous"] and list(res["event_of"]) == list(range(1, 400))


def test_a_missing_stretch_and_a_burst_of_spurious_detections():
    # the array was off for the first third of the session and heard a rattle (chirp-like clicks every
    # 0.2 s for a minute) later: the line is found from the events it did record
    det, score, t_emit, truth, drift = clock_scene(300, seed=11, miss=0.0, n_spurious=0)
    lost = truth < 100
    det, score, truth = det[~lost], score[~lost], truth[~lost]
    t0 = np.sort(det)[50]
    rattle = t0 + 0.05 + 0.2 * np.arange(300)
    near = np.min(np.abs(rattle[:, None] - det[None]), axis=1) < 0.15
    rattle = rattle[~near]
    res = associate(np.r_[det, rattle], np.r_[score, np.full(len(rattle), 15.0)], t_emit)
    np.testing.assert_array_equal(res["event_of"], np.r_[truth, np.full(len(rattle), -1)])
    assert list(np.flatnonzero(res["det_of"] < 0)) == list(range(100))


def test_overlapping_tolerance_windows_are_assigned_one_to_one():
    # a tolerance wider than half the spacing: every detection is a candidate for two events, so the
    # sorted merge alone cannot decide and the groups go to the assignment solver
    t_emit = np.cumsum(np.r_[0.0, np.random.default_rng(2).uniform(0.9, 1.1, 59)])
    arrivals = 3.0 + t_emit + 0.05
    keep = np.ones(60, bool)
    keep[[5, 30]] = False
    res = associate(arrivals[keep], np.ones(58), t_emit, tol=0.7)
    np.testing.assert_array_equal(res["event_of"], np.flatnonzero(keep))


# ----------------------------------------------------------------------------------------------- audio
def chirp_session(path, fs, seconds, starts, amps, channels=2, subtype="PCM_16", noise=0.01, seed=0):
    """A WAV of ``seconds`` with unit-template chirps (0.2 s, 500–4000 Hz) of amplitude ``amps`` starting at
    sample ``starts`` on every channel, plus white noise. Returns the array dict and the template."""
    n_t = int(0.2 * fs)
    tmpl = sweep(np.arange(n_t) / fs, 500.0, 4000.0, 0.2, 0.005)
    rng = np.random.default_rng(seed)
    n = int(seconds * fs)
    with sf.SoundFile(path, "w", fs, channels, subtype) as f:
        for b0 in range(0, n, 10 * fs):
            b1 = min(n, b0 + 10 * fs)
            blk = rng.normal(0, noise, (b1 - b0, channels))
            for s0, a in zip(starts, amps):
                lo, hi = max(s0, b0), min(s0 + n_t, b1)
                if hi > lo:
                    blk[lo - b0 : hi - b0] += a * tmpl[lo - s0 : hi - s0, None]
            f.write(blk)
    return {"name": "A", "wav": path, "mics": np.zeros((channels, 3))}, tmpl


def test_envelope_block_wise_finds_every_chirp_at_its_amplitude(tmp_path):
    fs = 16000
    starts = np.array([100, 40000, 262000, 262144 - 1600, 530000, 955000])  # one across a block edge
    amps = np.array([0.3, 0.5, 0.2, 0.4, 0.25, 0.35])
    arr, tmpl = chirp_session(tmp_path / "a.wav", fs, 60, starts, amps)
    band = (500.0, 4000.0)
    with ArrayAudio(arr) as x:
        env, dec = matched_envelope(x.channel_sum(), tmpl, fs, band, block=1 << 15)
        env_big, dec_big = matched_envelope(x.channel_sum(), tmpl, fs, band, block=1 << 22)  # one block
    assert dec == dec_big and len(env) == len(env_big) == -(-60 * fs // dec)
    assert np.max(np.abs(env - env_big)) < 1e-3 * np.max(env)  # blocks change nothing that matters
    # independent truth: a clean chirp of amplitude a gives an envelope peak of ≈ 2a (two channels summed)
    # at its start sample
    for s0, a in zip(starts, amps):
        k = s0 // dec
        win = env[max(k - 5, 0) : k + 6]
        assert abs(max(k - 5, 0) + np.argmax(win) - s0 / dec) <= 1
        # the decimated envelope (dec ≈ fs / 1.25 B) samples the peak, |sinc(B t)|-shaped, within half a
        # step of its top: at least sinc(0.4) ≈ 0.76 of it
        assert 0.75 * 2 * a < win.max() < 1.03 * 2 * a


def test_array_audio_segments_equal_the_file(tmp_path):
    fs = 8000
    rng = np.random.default_rng(0)
    data = rng.uniform(-0.5, 0.5, (3000, 3))
    for subtype in ("PCM_16", "PCM_24", "FLOAT"):
        p = tmp_path / f"{subtype}.wav"
        sf.write(p, data, fs, subtype=subtype)
        ref = sf.read(p, dtype="float32", always_2d=True)[0]
        padded = np.vstack([np.zeros((50, 3), np.float32), ref, np.zeros((50, 3), np.float32)])
        with ArrayAudio({"name": "A", "wav": p, "mics": np.zeros((3, 3))}) as x:
            assert x.shape == (3, 3000) and x.fs == fs
            np.testing.assert_array_equal(x[:, -50:3050], padded.T)
            np.testing.assert_array_equal(x[:, 1000:1001], ref[1000:1001].T)
            np.testing.assert_allclose(x.channel_sum()[:, -50:3050][0], padded.sum(axis=1), atol=1e-6)
            x.release()  # pages and buffers dropped: the same samples are read again
            np.testing.assert_array_equal(x[:, -50:3050], padded.T)
            np.testing.assert_allclose(x.channel_sum()[:, -50:3050][0], padded.sum(axis=1), atol=1e-6)
        whole, fs_read = read_array_audio({"name": "A", "wav": p, "mics": np.zeros((3, 3))})
        np.testing.assert_array_equal(whole, ref.T)
        assert fs_read == fs


def _float_wav_with(tmp_path, value):
    """A 2-channel float WAV, silent but for ``value`` at frame 3000 of channel 1 (as a session array)."""
    p = tmp_path / "nan.wav"
    data = np.zeros((4000, 2))
    data[3000, 1] = value
    sf.write(p, data, 8000, subtype="FLOAT")
    return {"name": "A", "wav": p, "mics": np.zeros((2, 3))}


def test_non_finite_samples_are_bad_input_when_read(tmp_path):
    with ArrayAudio(_float_wav_with(tmp_path, np.nan)) as x:
        assert np.all(x[:, 0:2000] == 0)
        with pytest.raises(InputError, match="nan.wav: contains non-finite samples"):
            x[:, 2000:4000]


def test_envelope_memory_does_not_grow_with_the_recording(tmp_path):
    # 4 minutes of 4-channel 48 kHz audio: 184 MB as float32 in memory. The envelope holds one block
    fs = 48000
    arr, tmpl = chirp_session(tmp_path / "long.wav", fs, 240, [fs, 100 * fs], [0.3, 0.3], channels=4)
    band = (500.0, 4000.0)
    with ArrayAudio(arr) as x:
        tracemalloc.start()
        env, dec = matched_envelope(x.channel_sum(), tmpl, fs, band)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak < env.nbytes + 40e6, f"{peak / 1e6:.0f} MB traced (envelope {env.nbytes / 1e6:.0f} MB)"
    assert abs(np.argmax(env) * dec - fs) <= dec or abs(np.argmax(env) * dec - 100 * fs) <= dec


def test_timing_in_chunks_equals_timing_at_once():
    # the timing stage reads and processes events a chunk at a time: with the carrier phase fixed the
    # result does not depend on the chunking; without it, the phase comes from the first chunk
    from pathlib import Path

    from calib.frontend.extract import locate_events
    from calib.frontend.signals import chirp_template
    from calib.frontend.timing import locate, segment_spectra, spectra_setup

    wav = Path(__file__).resolve().parents[1] / "sample_data" / "lab3" / "A1.wav"
    arr = {"name": "A1", "wav": wav, "mics": np.zeros((6, 3))}
    with ArrayAudio(arr) as x:
        tmpl = chirp_template({"reference": wav.parent / "chirp.wav"}, x.fs)
        env, dec = matched_envelope(x.channel_sum(), tmpl, x.fs, (500.0, 4000.0))
        peaks = np.flatnonzero((env > 0.5 * env.max()) & (env >= np.maximum(np.roll(env, 1), np.roll(env, -1))))
        starts = peaks * dec - 200
        setup = spectra_setup(tmpl, x.fs, (500.0, 4000.0), len(tmpl) + 600)
        kw = {"lo": 100, "hi": 300, "half_width": 10, "gate": 20}
        c, c_plain = segment_spectra(x, starts, setup, plain=True)
        whole = locate(c, setup, **kw, c_onset=c_plain)
        fixed = locate_events(x, starts, setup, {**kw, "phase": whole["phase"]}, chunk_bytes=1)  # 1 per chunk
        # the spectra are single precision: a different batch shape may round differently (numpy 1.26 and
        # 2.x differ here by ~2e-12 s), far below the 1 µs scale of timing noise
        np.testing.assert_allclose(fixed["tau"], whole["tau"], rtol=0, atol=1e-10)
        np.testing.assert_array_equal(fixed["dp"], whole["dp"])
        # locate_events keeps only the DOA gate's lags around each direct path
        idx = (whole["dp"] - 20 - whole["r_lo"])[:, None] + np.arange(41)
        window = np.take_along_axis(whole["r"], idx[:, None, :], axis=-1)
        np.testing.assert_array_equal(fixed["r_lo"], whole["dp"] - 20)
        np.testing.assert_allclose(fixed["r"], window, rtol=1e-6, atol=1e-6 * np.abs(window).max())
        first = locate_events(x, starts, setup, kw, chunk_bytes=1)
        c1, c1_plain = segment_spectra(x, starts[:1], setup, plain=True)
        assert first["phase"] == locate(c1, setup, **kw, c_onset=c1_plain)["phase"]
    assert len(starts) >= 10


def test_non_finite_sample_late_in_a_recording_is_one_clear_error(tmp_path):
    # the recording is read in blocks, so a NaN far into it is found mid-way: still one error line,
    # exit 2, nothing written
    import shutil
    from pathlib import Path

    from typer.testing import CliRunner

    from calib.cli.main import app
    from calib.pipeline.features import session_features

    d = tmp_path / "rec"
    shutil.copytree(Path(__file__).resolve().parents[1] / "sample_data" / "lab3", d)
    x, fs = sf.read(d / "A2.wav", always_2d=True)
    x[int(0.9 * len(x)), 3] = np.nan
    sf.write(d / "A2.wav", x, fs, subtype="FLOAT")
    with pytest.raises(InputError, match="A2.wav: contains non-finite samples"):
        session_features(d)
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["features", str(d), "-o", str(out / "features"), "-q"])
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and "A2.wav" in lines[0]
    assert not out.exists()


def test_non_finite_samples_are_bad_input_in_sums_and_segments(tmp_path):
    with ArrayAudio(_float_wav_with(tmp_path, np.inf)) as x:
        assert np.all(x.channel_sum()[:, 0:2000] == 0)
        with pytest.raises(InputError, match="nan.wav: contains non-finite samples"):
            x.channel_sum()[:, 2000:4000]
        with pytest.raises(InputError, match="nan.wav: contains non-finite samples"):
            x.fill_segment(np.zeros((2, 100), np.float32), 2950)


