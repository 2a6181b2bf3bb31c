"""One validation layer for every input: typed values, finiteness, documented physical ranges, unknown keys.

Every reader of session.toml, events.csv, meta.json, the feature/calibration/truth CSVs and every CLI
option checks its values here, so one value has one rule and one message. Problems raise
:class:`calib.errors.InputError` (``<file>: <problem>``); suspicious but usable values warn with
:class:`calib.errors.InputWarning`. The ranges are documented in docs/reliability.md.

Conventions for text inputs (the same for CSV, JSON and TOML):

- a UTF-8 byte-order mark is ignored, CRLF line ends are accepted;
- typed formats (JSON, TOML) need real numbers: ``"343"`` (a string) and ``true`` (a boolean) are errors;
- CSV cells are text by nature and are parsed as numbers (surrounding spaces ignored).
"""
from __future__ import annotations

import difflib
import math
import numbers
import os
import warnings
from pathlib import Path

import numpy as np

from calib.errors import InputError, InputWarning
from calib.kinds import noise_keys

BOM = "\ufeff"

# ---- documented ranges (docs/reliability.md); SI units
SPEED_OF_SOUND = (150.0, 2000.0)      # m/s: any gas to water; air is ~343
SAMPLE_RATE = (1000, 1_000_000)       # Hz, WAV sample rates the frontend handles
MAX_ABS_POSITION = 1e5                # m: coordinates, odometry (100 km; beyond is a unit mistake)
MAX_ABS_TIME = 1e7                    # s: emission times, TDOAs, offsets (~115 days)
MAX_ABS_DRIFT = 0.01                  # clock drift (1 %: far beyond any real crystal)
MAX_EVENT_ID = 10**9
MAX_EVENTS = 10_000                   # events in one session (memory of the frontend and estimator)
MAX_ARRAYS = 256
MAX_MICS = 64                         # mics per array
MAX_CHANNELS = 1024                   # channels of one WAV (a channel map's indices are below this)
MIN_MIC_SPACING = 1e-3                # m: closer mics are the same mic (a typo)
CHIRP_DURATION = (1e-3, 60.0)         # s
MIN_DIRECTION_NORM = 1e-9             # a direction vector shorter than this has no direction
# The estimator's working set (:func:`estimator_memory`), so that a problem is refused only when the solver
# that runs (sparse above ~300 parameters) cannot fit; benchmarks/bench_scale.py checks it against the peak RSS
# of `calib estimate`.
JACOBIAN_WIDTH = {"tdoa_m": 9, "tdoa_s": 10, "doa": 9, "odometry": 2}  # free columns of one scalar row, at most
BYTES_PER_JACOBIAN_ENTRY = 100   # per entry, alive at the peak: the current and the candidate CSR Jacobians
#                                  (12 B each, 32-bit indices), a factor's chunk while it is stacked (16 B), H,
#                                  Jᵀ and W J of the normal equations (36 B), robust statistics. Measured peak RSS of
#                                  `calib estimate`: 40 × 1000 358 MB (predicted 396), 100 × 5000 2570 MB (2808)
DENSE_EVENT_ARRAY_BLOCKS = 3     # dense (event parameters × array parameters) blocks: H_EA, X = H_EE⁻¹ H_EA, X S⁻¹
ESTIMATOR_BASE_BYTES = 150 * 2**20  # the interpreter, numpy/scipy/pandas and the calib modules (measured)
ESTIMATOR_PER_ARRAY_BYTES = 2**20   # per array, whatever the events (measured: 40 × 200 peaks 38 MB above 10 × 200)


def strip_bom(text):
    """Text without a leading UTF-8 byte-order mark."""
    return text[1:] if text.startswith(BOM) else text


def read_text(path):
    """Read a UTF-8 text file (BOM dropped, CRLF → LF). Raises InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text") from None
    return strip_bom(text).replace("\r\n", "\n")


def number(value, where, *, lo=None, hi=None, lo_open=False, integer=False, allow_none=False):
    """A typed number from JSON/TOML/CLI: not a bool or string, finite, within [lo, hi] (lo open if asked).

    where : "<file>: '<key>'" or "--option", the start of the message.
    Returns float (or int when ``integer``), or None for None when ``allow_none``.
    """
    if value is None and allow_none:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise InputError(f"{where} must be a number, not {show(value)}")
    if isinstance(value, numbers.Integral) and abs(int(value)) > 1e300:
        raise InputError(f"{where} is out of range: {show(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{where} must be finite, not {v}")
    if integer and v != int(v):
        raise InputError(f"{where} must be an integer, not {v:g}")
    check_range(v, where, lo=lo, hi=hi, lo_open=lo_open)
    return int(v) if integer else v


def check_range(v, where, *, lo=None, hi=None, lo_open=False):
    """Raise InputError unless ``lo <= v <= hi`` (``lo < v`` when ``lo_open``)."""
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise InputError(f"{where} must be {'>' if lo_open else '≥'} {lo:g}, not {v:g}")
    if hi is not None and v > hi:
        raise InputError(f"{where} must be ≤ {hi:g}, not {v:g}")


def string(value, where, *, allow_empty=False):
    """A typed non-empty string."""
    if not isinstance(value, str) or (not value and not allow_empty):
        raise InputError(f"{where} must be a {'' if allow_empty else 'non-empty '}string, not {show(value)}")
    return value


def vector3(value, where, *, nonzero=False, bound=MAX_ABS_POSITION):
    """A list of three finite numbers (no booleans, no strings) → tuple of floats."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise InputError(f"{where} must be [x, y, z], not {show(value)}")
    v = tuple(number(x, where, lo=-bound, hi=bound) for x in value)
    if nonzero and not math.hypot(*v) > MIN_DIRECTION_NORM:
        raise InputError(f"{where} must be a non-zero direction")
    return v


def sigma(key, value, where):
    """A noise figure of meta.json / session.toml within its documented range (``calib.kinds``: noise_range)."""
    lo, hi = noise_keys()[key]
    return number(value, where, lo=lo, hi=hi, lo_open=True)


def speed_of_sound(value, where):
    return number(value, where, lo=SPEED_OF_SOUND[0], hi=SPEED_OF_SOUND[1])


def check_keys(table, known, where):
    """Warn (InputWarning) about keys of ``table`` not in ``known``, suggesting the closest known key."""
    for key in table:
        if key in known:
            continue
        close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
        hint = f" (did you mean '{close[0]}'?)" if close else f" (known: {', '.join(sorted(known))})"
        warnings.warn(f"{where}: unknown key '{key}' ignored{hint}", InputWarning, stacklevel=2)


def memory_limit():
    """Bytes this process can have: the physical memory, or less where a cgroup (container) or ulimit caps it."""
    try:
        limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        limit = float("inf")
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            limit = min(limit, int(text))
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            limit = min(limit, soft)
    except (ImportError, ValueError, OSError):
        pass
    return limit


def jacobian_entries(n_events, rows):
    """Non-zeros of the estimator's Jacobian (at most): ``JACOBIAN_WIDTH`` per scalar row of each kind in
    ``rows`` (kind → scalar rows), plus the odometry rows of ``n_events`` events."""
    rows = {**rows, "odometry": 3 * max(n_events - 1, 0)}
    return sum(JACOBIAN_WIDTH.get(k, max(JACOBIAN_WIDTH.values())) * m for k, m in rows.items())


def estimator_memory(n_events, n_arrays, rows):
    """Peak bytes of a calibration (``calib estimate``) of ``n_events`` × ``n_arrays`` with ``rows`` (dict:
    measurement kind → scalar residual rows; a DOA counts 3), for the sparse solver that runs above
    ``estimator.solver.DENSE_MAX_PARAMS`` (300) parameters.

    A base and ``ESTIMATOR_PER_ARRAY_BYTES`` per array, ``BYTES_PER_JACOBIAN_ENTRY`` per non-zero of the
    Jacobian (``JACOBIAN_WIDTH`` per row), the Schur complement's dense event × array blocks and a few copies
    of the dense array block. Parameters: 3 per event (source), 10 per array (position, rotation, offset,
    drift). The dense path's problems (≤ 300 parameters: ≤ 100 events) take a few tens of MB, within
    ``ESTIMATOR_BASE_BYTES``. Within −2 … +15 % of the measured peak RSS of `calib estimate` from 5 × 100 to
    40 × 1000 (benchmarks/bench_scale.py, column pred/peak).
    """
    n_ev, n_ar = 3 * n_events, 10 * n_arrays
    return (ESTIMATOR_BASE_BYTES + ESTIMATOR_PER_ARRAY_BYTES * n_arrays
            + BYTES_PER_JACOBIAN_ENTRY * jacobian_entries(n_events, rows)
            + 8.0 * (DENSE_EVENT_ARRAY_BLOCKS * n_ev * n_ar + 3 * n_ar * n_ar))


def check_problem_size(n_events, n_arrays, rows, where):
    """Refuse an estimation whose working set (:func:`estimator_memory`) exceeds this machine's memory.

    rows : dict measurement kind → scalar residual rows (a DOA counts 3).
    """
    need, limit = estimator_memory(n_events, n_arrays, rows), memory_limit()
    if need > limit:
        raise InputError(f"{where}: {n_events} events × {n_arrays} arrays with {sum(rows.values())} measurements "
                         f"need about {need / 2**30:.3g} GiB for the estimator, more than the {limit / 2**30:.3g} "
                         "GiB of memory here; split the session")


# ---------------------------------------------------------------------------------------------- CLI options
def option(value, name, *, lo=None, hi=None, lo_open=False, integer=False, allow_none=True):
    """A numeric CLI option (``--name``): finite and in range. None (not given) passes when allowed."""
    if value is None and allow_none:
        return None
    return number(value, f"--{name}", lo=lo, hi=hi, lo_open=lo_open, integer=integer)


def choice(value, name, allowed):
    """A CLI option from a fixed set."""
    if value not in allowed:
        raise InputError(f"--{name} must be {', '.join(allowed[:-1])} or {allowed[-1]}, not {value!r}")
    return value


def show(value):
    """A value as a message shows it: its repr, cut to 40 characters."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


# ---------------------------------------------------------------------------------------------- command options
DETECT_THRESHOLD = (1.0, 1e6)      # matched-filter peak over local background
MAX_DRIFT = (1e-9, MAX_ABS_DRIFT)  # bound on |clock drift| for association


def estimate_options(opts):
    """Validate estimator options (the flagged ones of ``calib.estimator.options.OPTIONS``).

    Messages name the CLI option (``--outlier-threshold``). Returns a cleaned copy.
    """
    from calib import options as O

    out = dict(opts)
    for o in O.cli_options():
        if o.name not in out:
            continue
        if o.choices:
            choice(out[o.name], o.name, tuple(c for c in o.choices if c is not None))
        elif o.kind is float:
            out[o.name] = option(out[o.name], o.name.replace("_", "-"), lo=o.lo, hi=o.hi, lo_open=o.lo_open,
                                 allow_none=False)
    try:  # the estimator's own check of its options (the library API uses it too) has the last word
        O.validate_options(**out)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return out


def jobs_option(jobs):
    """``jobs`` (arrays processed at a time): a positive integer or −1 (one per core). Returns it."""
    if jobs != -1:
        option(jobs, "jobs", lo=1, hi=1024, integer=True)
    return int(jobs)


def features_options(opts):
    """Validate frontend options given on the command line (threshold, max_drift). Returns a cleaned copy."""
    out = dict(opts)
    if out.get("threshold") is not None:
        out["threshold"] = option(out["threshold"], "detect-threshold", lo=DETECT_THRESHOLD[0],
                                  hi=DETECT_THRESHOLD[1])
    if out.get("max_drift") is not None:
        out["max_drift"] = option(out["max_drift"], "max-drift", lo=MAX_DRIFT[0], hi=MAX_DRIFT[1])
    return out
