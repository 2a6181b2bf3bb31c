"""The estimator's options, declared once (scikit-learn's declared parameters): default, allowed values,
CLI flag and help text of each keyword of ``calib.estimator.calibrate``.

``calibrate_features``' signature (and ``estimator.clockmodel.calibrate_clocks``' for ``clock_model``) repeats
the defaults for its readers (tests/test_options.py holds them equal); ``validate_options`` (the library's check), the ``calib estimate`` / ``calib run`` options (``cli/common.py``), the CLI's input check
(``pipeline/formats/validate.py``), the stage key's settings (``pipeline/run.py``) and docs/cli.md (a test)
are loops over :data:`OPTIONS`. In the core so that the CLI declares its flags without loading the estimator.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Option:
    """One keyword option of ``calibrate``.

    name : the keyword. default : its value when not given. kind : ``str`` (then ``choices``), ``float``, ``int`` or ``bool``.
    choices : allowed values (``None`` among them is an alias the CLI does not show).
    lo, hi : allowed range of a number, ``lo < v`` when ``lo_open`` else ``lo <= v``, and ``v <= hi``.
    flag : the CLI spelling (``None``: library only); a bool's flag switches the default
        (``--no-tdoa-s`` sets ``use_tdoa_s`` False). help : the CLI / docs text.
    """
    name: str
    default: Any
    kind: type
    help: str = ""
    choices: tuple = ()
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    flag: str | None = None

    def check(self, value: Any) -> None:
        """Raise ValueError naming the option when ``value`` is not allowed (NaN, inf, wrong type)."""
        if self.choices:
            if value not in self.choices:
                shown = [a for a in self.choices if a is not None]
                raise ValueError(f"{self.name} must be {', '.join(shown[:-1])} or {shown[-1]}, not {value!r}")
        elif self.kind is bool:
            if not _is_bool(value):
                raise ValueError(f"{self.name} must be True or False, not {value!r}")
        elif self.kind is int:
            if _is_bool(value) or not _is_int(value) or not self.lo <= value <= self.hi:
                raise ValueError(f"{self.name} must be an integer >= {self.lo:g}, not {value!r}")
        else:
            try:
                f = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{self.name} must be a number, not {value!r}") from None
            if not math.isfinite(f) or (f <= self.lo if self.lo_open else f < self.lo) or f > self.hi:
                bound = f"{'>' if self.lo_open else '>='} {self.lo:g}" + (f" and <= {self.hi:g}"
                                                                        if math.isfinite(self.hi) else "")
                raise ValueError(f"{self.name} must be a finite number {bound}, not {value!r}")


def _is_bool(v):
    return type(v).__name__ in ("bool", "bool_")


def _is_int(v):
    import numpy as np

    return isinstance(v, (int, np.integer))


OPTIONS = (  # in the order ``calib estimate --help`` shows the flagged ones
    Option("method", "hybrid", str, "estimator: hybrid (ours) or wang (baseline, no TDOA-S)", choices=("hybrid", "wang"),
           flag="--method"),
    Option("use_tdoa_s", True, bool, "ignore TDOA-S (Wang et al.'s measurement set)", flag="--no-tdoa-s"),
    Option("emission_sigma", 0.0, float, "prior std (s) of emission-interval errors to estimate; 0 = off", lo=0.0,
           hi=10.0, flag="--emission-sigma"),
    Option("loss", "cauchy", str, "robust loss on TDOA residuals: cauchy, huber or linear",
           choices=("cauchy", "huber", "linear", None), flag="--loss"),
    Option("outlier_threshold", 5.0, float, "flag and drop measurements (TDOA, DOA, odometry) whose normalised residual "
           "exceeds this many sigmas (or the Bonferroni level, if larger)", lo=1.0, hi=1e3,
           flag="--outlier-threshold"),
    Option("noise", "auto", str, "weights: auto (re-estimate the frontend's own noise figures from the residuals), meta "
           "(meta.json's sigmas as they are) or estimate", choices=("auto", "meta", "estimate"), flag="--noise"),
    Option("array_noise", False, bool, "when noise figures are re-estimated: also one figure per measurement type and "
           "array where the data allow it (an array noisier than the rest is down-weighted instead of distorting "
           "the others)", flag="--array-noise"),
    Option("clock_model", "auto", str, "each array's clock: auto (one offset and drift, plus clock steps from dropped "
           "or inserted sample blocks and a varying drift where the evidence asks for them), or linear (never more)",
           choices=("linear", "auto"), flag="--clock-model"),
    Option("target_position", 0.03, float, "precision asked of each array's position, m: an array whose std gives "
           "its error more than a 20 % chance of lying beyond it is named (verdict suspect); 0 = off", lo=0.0, hi=100.0,
           flag="--target-position"),
    Option("target_orientation_deg", 1.5, float, "precision asked of each array's orientation, degrees (as "
           "--target-position); 0 = off", lo=0.0, hi=180.0, flag="--target-orientation"),
    Option("robust_k", 3.0, float, "robust scale, in units of each type's sigma", lo=0.0, lo_open=True),
    Option("max_iter", 200, int, "iterations of each Levenberg-Marquardt solve", lo=1),
    Option("odometry_yaw", True, bool, "estimate the odometry frame's yaw (kept only when significant)"),
    # (fixed by default: the data fix c only against the odometry's scale, docs/method.md "Speed of sound")
    Option("speed_of_sound", "fixed", str, "speed of sound: fixed (as declared) or auto (solved with the rest where "
           "the data tell it from the declared value: trusts the odometry's metres over the declared c)",
           choices=("fixed", "auto"), flag="--speed-of-sound"),
    # c in air is 331.3 + 0.606·T m/s: 343 m/s declared without a thermometer is off by up to ±3.5 % over 0–40 °C
    Option("speed_of_sound_sigma", 0.035, float, "relative 1-σ of the declared speed of sound (its prior when solved): "
           "0.035 for a c declared without a thermometer (0–40 °C), ~0.005 when taken from the measured air "
           "temperature", lo=0.0, lo_open=True, hi=0.5, flag="--speed-sigma"),
    Option("outputs", "all", str, "all, or solution (the solve only)", choices=("all", "solution")),
)
OPTION = {o.name: o for o in OPTIONS}
DEFAULTS = {o.name: o.default for o in OPTIONS}
# keywords of calibrate that are data or a callback (clock_veto), not options (not checked here); readmit: the
# leave-one-array-out test's isolated arrays that may come back with their clock terms (clockmodel._readmit)
INPUTS = ("init_state", "problem", "isolate", "clock_veto", "readmit")


def cli_options() -> tuple[Option, ...]:
    """The options ``calib estimate`` and ``calib run`` take, in --help order."""
    return tuple(o for o in OPTIONS if o.flag)


def validate_options(**options: Any) -> None:
    """Raise ValueError with a clear message for any option of ``calibrate_features`` out of range.

    The one place the estimator options are checked (the CLI and ``pipeline.run`` call it before reading
    any data): NaN, infinities and negative values are refused, never silently used. Unknown keywords
    raise TypeError; the data keywords (``INPUTS``) pass.
    """
    for name, value in options.items():
        if name in OPTION:
            OPTION[name].check(value)
        elif name not in INPUTS:
            raise TypeError(f"unknown estimator option {name!r}")
