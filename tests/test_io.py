"""Readers reject bad input with one line naming the file, the row and the problem; writers are atomic."""
import json
import subprocess
import sys

import numpy as np
import pytest

from calib.pipeline.simulate.featsim import simulate_features
from calib.pipeline.formats.io import InputError, read_features, write_calibration, write_features, read_calibration


@pytest.fixture
def features_dir(tmp_path):
    feats, _ = simulate_features(1, seed=0)
    d = tmp_path / "features"
    write_features(d, feats)
    return d


def edit(path, old, new, count=1):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, count))


def test_round_trip(features_dir):
    f = read_features(features_dir)
    assert len(f["tdoa_m"]) == 4 * 8 and len(f["tdoa_s"]) == 5 * 7 and len(f["doa"]) == 5 * 8
    assert np.allclose(np.linalg.norm(f["doa"][["ux", "uy", "uz"]], axis=1), 1)


def _line_of(path, prefix):
    return next(k + 1 for k, line in enumerate(path.read_text().splitlines()) if line.startswith(prefix))


@pytest.mark.parametrize("case", ["missing_column", "nan", "inf", "unknown_array", "duplicate", "not_unit",
                                  "unknown_event", "not_a_number"])
def test_bad_features_name_file_row_and_problem(features_dir, case):
    tm, doa = features_dir / "tdoa_m.csv", features_dir / "doa.csv"
    first_row = tm.read_text().splitlines()[1]
    if case == "missing_column":
        edit(tm, "event,array,tdoa", "event,array,value")
        target, msg = tm, "missing column"
    elif case in ("nan", "inf", "not_a_number"):
        value = first_row.split(",")[2]
        edit(tm, first_row, first_row.replace(value, {"nan": "nan", "inf": "inf", "not_a_number": "abc"}[case]))
        target, msg = tm, "line 2"
    elif case == "unknown_array":
        edit(tm, first_row, first_row.replace(",A2,", ",B7,"))
        target, msg = tm, "unknown array 'B7'"
    elif case == "duplicate":
        tm.write_text(tm.read_text() + first_row + "\n")
        target, msg = tm, "duplicate row"
    elif case == "not_unit":
        row = doa.read_text().splitlines()[3]
        ux = row.split(",")[2]
        edit(doa, row, row.replace(ux, str(float(ux) + 0.1), 1))
        target, msg = doa, "not a unit vector"
    elif case == "unknown_event":
        edit(tm, first_row, "99" + first_row[first_row.index(","):])
        target, msg = tm, "unknown event id 99"
    with pytest.raises(InputError) as err:
        read_features(features_dir)
    text = str(err.value)
    assert str(target) in text and msg in text and "\n" not in text


def test_nearly_unit_doa_is_renormalised(features_dir):
    doa = features_dir / "doa.csv"
    lines = doa.read_text().splitlines()
    parts = lines[1].split(",")
    parts[2:5] = [repr(float(v) * 1.0005) for v in parts[2:5]]
    lines[1] = ",".join(parts)
    doa.write_text("\n".join(lines) + "\n")
    f = read_features(features_dir)
    assert np.allclose(np.linalg.norm(f["doa"][["ux", "uy", "uz"]], axis=1), 1, atol=1e-12)


def test_bad_meta(features_dir):
    meta = json.loads((features_dir / "meta.json").read_text())
    meta["reference_array"] = "nope"
    (features_dir / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="meta.json.*reference_array"):
        read_features(features_dir)


@pytest.mark.slow
def test_cli_bad_input_exit_code_2_and_nothing_written(features_dir, tmp_path):
    edit(features_dir / "doa.csv", "event,array,ux", "event,arr,ux")
    out = tmp_path / "calibration"
    res = subprocess.run([sys.executable, "-m", "cli.main", "estimate", str(features_dir), "-o", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 2
    assert res.stderr.startswith("error: ") and str(features_dir / "doa.csv") in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not out.exists() and not list(tmp_path.glob(".calibration*"))


def test_failed_write_leaves_previous_output_intact(tmp_path):
    feats, truth = simulate_features(1, seed=0)
    out = tmp_path / "calibration"
    write_calibration(out, {**truth, "report": {"ok": 1}})
    with pytest.raises(TypeError):
        write_calibration(out, {**truth, "report": {"bad": object()}})
    assert read_calibration(out)["report"] == {"ok": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration"]


def test_outputs_are_readable_by_others(tmp_path):
    import os
    import stat

    feats, _ = simulate_features(1, seed=0)
    write_features(tmp_path / "features", feats)
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE((tmp_path / "features").stat().st_mode) == 0o777 & ~mask
    assert stat.S_IMODE((tmp_path / "features" / "doa.csv").stat().st_mode) == 0o666 & ~mask


def test_read_features_rows_carry_their_csv_line_and_no_private_columns(tmp_path):
    """Rows keep their file line (header = 1) even after sorting; the column is never written back."""
    feats, _ = simulate_features(1, seed=3)
    write_features(tmp_path / "f", feats)
    path = tmp_path / "f" / "tdoa_m.csv"
    lines = path.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    path.write_text("\n".join([header] + rows[::-1]) + "\n")   # reversed on disk: readers sort
    back = read_features(tmp_path / "f")
    tm = back["tdoa_m"]
    assert not any(str(c).startswith("_") for k in ("events", "tdoa_m", "tdoa_s", "doa") for c in back[k].columns)
    for _, r in tm.iterrows():
        on_disk = lines[0:1] + rows[::-1]
        fields = on_disk[int(r["csv_line"]) - 1].split(",")
        assert int(fields[0]) == r["event"] and fields[1] == r["array"]
    write_features(tmp_path / "g", back)
    assert "csv_line" not in (tmp_path / "g" / "tdoa_m.csv").read_text().splitlines()[0]


def _with_row_sigmas(d, cells):
    """doa.csv with a sigma_deg column: ``cells`` cycled over its rows."""
    p = d / "doa.csv"
    lines = p.read_text().splitlines()
    lines[0] += ",sigma_deg"
    lines[1:] = [f"{line},{cells[k % len(cells)]}" for k, line in enumerate(lines[1:])]
    p.write_text("\n".join(lines) + "\n")
    return p


def test_doa_row_sigmas_are_read_as_numbers_and_empty_cells_as_nan(features_dir):
    _with_row_sigmas(features_dir, ["0.25", "", "1.5e-1"])
    s = read_features(features_dir)["doa"]["sigma_deg"].to_numpy()
    assert s.dtype == float
    np.testing.assert_array_equal(s[:3], [0.25, np.nan, 0.15])


@pytest.mark.parametrize("bad", ["-0.1", "0", "inf", "abc"])
def test_a_bad_doa_row_sigma_names_file_line_and_value(features_dir, bad):
    p = _with_row_sigmas(features_dir, ["0.2", bad])
    with pytest.raises(InputError) as err:
        read_features(features_dir)
    text = str(err.value)
    assert str(p) in text and "line 3" in text and "sigma_deg" in text and bad in text.rsplit("(got ", 1)[1]
