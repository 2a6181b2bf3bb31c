"""mypy is clean on calib (the public API is annotated): run on a mirror of the installed package layout.

mypy cannot follow setuptools' editable finder, so the test copies the folders to tmp/calib as
pyproject.toml's package-dir maps them (core/ → calib, frontend/ → calib/frontend, ...) and runs
``python -m mypy -p calib`` there. Skipped when mypy is not installed (it is in the ``test`` extra).
"""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from calib.tomlcompat import tomllib

ROOT = Path(__file__).resolve().parents[1]


def mirror_package(dest):
    """Copy the sources into ``dest/calib`` following pyproject.toml's package-dir. Returns dest."""
    dirs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name, folder in sorted(dirs.items(), key=lambda kv: kv[0].count(".")):  # the root package first
        shutil.copytree(ROOT / folder, dest.joinpath(*name.split(".")), ignore=skip, dirs_exist_ok=True)
    return dest


@pytest.mark.slow
def test_mypy_finds_no_errors(tmp_path):
    pytest.importorskip("mypy")
    mirror_package(tmp_path)
    res = subprocess.run([sys.executable, "-m", "mypy", "-p", "calib", "--ignore-missing-imports",
                          "--no-incremental", "--cache-dir", str(tmp_path / ".mypy_cache")],
                         cwd=tmp_path, capture_output=True, text=True)
    assert res.returncode == 0 and "Success" in res.stdout, res.stdout[-5000:] + res.stderr[-2000:]
