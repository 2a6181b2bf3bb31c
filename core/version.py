"""The installed version of calib (one place)."""
from importlib.metadata import PackageNotFoundError, version as _dist_version

DIST_NAME = "calib-arrays"


def _lookup():
    try:
        return _dist_version(DIST_NAME)
    except PackageNotFoundError:  # running from a source tree that is not installed
        return "0+unknown"


__version__ = _lookup()
