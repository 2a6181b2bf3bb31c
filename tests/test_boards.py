"""Raw board layouts (channel maps) and one file per mic: session.toml, `calib init`, and the audio the
frontend reads (against the samples written, channel by channel)."""
import re

import numpy as np
import pandas as pd
import pytest
import soundfile as sf
from typer.testing import CliRunner

from calib.cli.main import app
from calib.errors import InputError
from calib.frontend.signals import ArrayAudio, read_header
from calib.pipeline.formats.boards import BOARDS
from calib.pipeline.formats.session import read_session

from .sessions import read_array_audio

FS = 16000


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def _signals(n_ch, n=3000, seed=0):
    """(n, n_ch) distinct test signals in [-0.5, 0.5] (each channel recognisable)."""
    return np.random.default_rng(seed).uniform(-0.5, 0.5, (n, n_ch))


def _events(d):
    pd.DataFrame({"event": [0, 1, 2], "t_emit": [0.02, 0.06, 0.1], "odom_x": [0.0, 0.5, 1.0], "odom_y": 0.0,
                  "odom_z": 0.0}).to_csv(d / "events.csv", index=False)


@pytest.mark.parametrize("subtype", ["PCM_16", "PCM_24", "FLOAT"])
@pytest.mark.parametrize("board", ["respeaker-6-circular", "respeaker-usb-4mic", "minidsp-uma8"])
def test_raw_layout_reads_the_mapped_channels_in_mic_order(tmp_path, board, subtype):
    b = BOARDS[board]
    x = _signals(b.raw_channels)
    sf.write(tmp_path / "A.wav", x, FS, subtype=subtype)
    got = sf.read(tmp_path / "A.wav", always_2d=True)[0]  # the stored (quantised) samples
    chans = list(b.channels)[::-1]  # any order: here the board's reversed
    a = {"name": "A", "wav": tmp_path / "A.wav", "mics": b.mic_array(), "channels": chans}
    y, fs = read_array_audio(a)
    assert fs == FS and y.shape == (len(chans), len(x))
    assert np.allclose(y, got[:, chans].T, atol=1e-6)
    with ArrayAudio(a) as audio:
        s = audio.segment(-5, 2000, channel_sum=True)  # the detector's sum: the mics only
        assert np.allclose(s[5:], got[:2000, chans].sum(axis=1), atol=1e-5) and np.all(s[:5] == 0)
        out = np.zeros((len(chans), 100), np.float32)
        audio.fill_segment(out, 700)
        assert np.allclose(out, got[700:800, chans].T, atol=1e-6)
    # without a map, the raw file does not fit the mics: one line naming the file and the way out
    with pytest.raises(InputError, match=f"A.wav: {b.raw_channels} channels, but array 'A' has {len(b.mics)} mics"):
        read_header({**a, "channels": None})
    with pytest.raises(InputError, match=f"maps a mic to channel {b.raw_channels}"):
        read_header({**a, "channels": [b.raw_channels] + chans[1:]})


def test_one_file_per_mic_stacks_the_files_and_checks_rate_and_length(tmp_path):
    x = _signals(4)
    for m in range(4):
        sf.write(tmp_path / f"arr1-{m + 1}.wav", x[:, m], FS, subtype="PCM_16")
    files = [tmp_path / f"arr1-{m + 1}.wav" for m in (2, 0, 1, 3)]
    a = {"name": "arr1", "wav": files[0], "files": files, "mics": np.eye(4, 3) * 0.05}
    got = np.stack([sf.read(f)[0] for f in files])
    y, fs = read_array_audio(a)
    assert fs == FS and np.allclose(y, got, atol=1e-6)
    with ArrayAudio(a) as audio:
        assert audio.shape == (4, len(x))
        assert np.allclose(audio.segment(10, 50, channel_sum=True), got[:, 10:50].sum(axis=0), atol=1e-5)
    sf.write(files[1], x[:-1, 0], FS)
    with pytest.raises(InputError, match="2999 frames, but arr1-3.wav has 3000"):
        read_header(a)
    sf.write(files[1], x[:, 0], 8000)
    with pytest.raises(InputError, match="8000 Hz, but arr1-3.wav has 16000 Hz"):
        read_header(a)
    sf.write(files[1], x[:, :2], FS)
    with pytest.raises(InputError, match="arr1-1.wav: 2 channels, but array 'arr1' lists one mono file per mic"):
        read_header(a)


def test_init_writes_the_channel_map_of_a_raw_recording_and_run_reads_it(tmp_path):
    b = BOARDS["respeaker-usb-4mic"]
    sf.write(tmp_path / "A.wav", _signals(b.raw_channels), FS)
    sf.write(tmp_path / "B.wav", _signals(len(b.mics), seed=1), FS)  # mics only: no map needed
    r = invoke("init", tmp_path, "--model", "respeaker-usb-4mic", "-q")
    assert r.exit_code == 0, r.output
    text = (tmp_path / "session.toml").read_text()
    assert "channels = [1, 2, 3, 4]" in text and "odaslive/respeaker_usb_4_mic_array.cfg" in text
    _events(tmp_path)
    s = read_session(tmp_path)
    assert s["arrays"][0]["channels"] == (1, 2, 3, 4) and s["arrays"][1]["channels"] is None
    assert np.allclose(s["arrays"][0]["mics"], b.mics)


def test_init_per_mic_layout_groups_the_files_by_array_in_mic_number_order(tmp_path):
    for i in (1, 2):
        for m in range(1, 12):  # 11 mics: arr1-10 sorts after arr1-9
            sf.write(tmp_path / f"arr{i}-{m}.wav", _signals(1, seed=m)[:, 0], FS)
    r = invoke("init", tmp_path, "--layout", "per-mic", "--model", "custom", "-q")
    assert r.exit_code == 0, r.output
    text = (tmp_path / "session.toml").read_text()
    rng = np.random.default_rng(0)  # fill in a geometry (custom leaves zeros)
    lines = [line if not line.startswith("mics") else "mics = " + str(rng.uniform(-0.1, 0.1, (11, 3)).tolist())
             for line in text.splitlines()]
    (tmp_path / "session.toml").write_text("\n".join(lines) + "\n")
    _events(tmp_path)
    s = read_session(tmp_path)
    assert [a["name"] for a in s["arrays"]] == ["arr1", "arr2"]
    assert [f.name for f in s["arrays"][0]["files"]] == [f"arr1-{m}.wav" for m in range(1, 12)]
    y, _ = read_array_audio(s["arrays"][1])
    assert np.allclose(y[9], sf.read(tmp_path / "arr2-10.wav")[0], atol=1e-4)
    # a stray file name: one line
    sf.write(tmp_path / "notes.wav", np.zeros(10), FS)
    r = invoke("init", tmp_path, "--layout", "per-mic", "-o", tmp_path / "s2.toml")
    assert r.exit_code == 2 and "notes.wav: not named <array>-<mic>.wav" in r.stderr


@pytest.mark.parametrize("arrays, message", [
    ('wav = "A.wav"\nfiles = ["A.wav"]', "either 'wav' (one multichannel file) or 'files'"),
    ('files = ["A.wav"]', "1 files for 2 mics"),
    ('wav = "A.wav"\nchannels = [0]', "must list one WAV channel per mic (2, counted from 0)"),
    ('wav = "A.wav"\nchannels = [1, 1]', "channel 1 is given for two mics"),
    ('wav = "A.wav"\nchannels = [0, -1]', "must be"),
    ('wav = "A.wav"\nchannels = [0, 1.5]', "must be an integer"),
])
def test_bad_channel_maps_and_file_lists_are_one_line_errors(tmp_path, arrays, message):
    sf.write(tmp_path / "A.wav", _signals(3), FS)
    _events(tmp_path)
    (tmp_path / "session.toml").write_text(f'[chirp]\nf0 = 500.0\nf1 = 4000.0\nduration = 0.01\n\n[[arrays]]\n'
                                           f'name = "A"\n{arrays}\nmics = [[0, 0, 0], [0.05, 0, 0]]\n')
    with pytest.raises(InputError, match=re.escape(message)) as exc:
        read_session(tmp_path)
    assert "\n" not in str(exc.value)
