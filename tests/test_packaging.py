"""Packaging: the lowest-versions CI pins are the floors pyproject.toml declares; the licence is there."""
import re
from calib.tomlcompat import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _name(req):
    return re.split(r"[<>=!\[; ]", req, maxsplit=1)[0].lower().replace("_", "-")


def _version(v):
    """'1.26' and '1.26.0' compare equal."""
    parts = [int(x) for x in v.split(".")]
    while parts and parts[-1] == 0:
        parts.pop()
    return tuple(parts)


def test_lowest_pins_are_the_declared_floors():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = project["dependencies"] + project["optional-dependencies"]["test"]
    floors = {_name(r): re.search(r">=([0-9][^,; ]*)", r).group(1) for r in reqs}
    pins = dict(line.split("==") for line in (ROOT / ".ci" / "lowest.txt").read_text().split("\n")
                if line and not line.startswith("#"))
    pins = {k.lower(): v for k, v in pins.items()}
    assert set(floors) <= set(pins), f"no pin for {set(floors) - set(pins)}"
    for name, floor in floors.items():
        assert _version(pins[name]) == _version(floor), f"{name}: pinned {pins[name]}, floor {floor}"
    assert "pytest" not in {_name(r) for r in project["dependencies"]}  # a test extra, not a runtime dependency


def test_license_file_is_mit():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


@pytest.mark.slow
def test_wheel_declares_its_annotations(tmp_path):
    """PEP 561: the built wheel carries calib/py.typed, so type checkers read calib's annotations."""
    import subprocess
    import sys
    import zipfile
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                    "-w", str(tmp_path), str(ROOT)], check=True, capture_output=True)
    (wheel,) = tmp_path.glob("calib_arrays-*.whl")
    assert "calib/py.typed" in zipfile.ZipFile(wheel).namelist()
