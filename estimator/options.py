"""The estimator's options, declared once (scikit-learn's declared parameters).

Each option's default is the default of its keyword in :func:`calib.estimator.calibrate.calibrate_features`
(the signature a reader of the maths sees); its allowed values, its CLI flag and its help text are declared
here. ``validate_options`` (the library's check), the ``calib estimate`` / ``calib run`` options
(``cli/common.py``), the CLI's input check (``pipeline/formats/validate.py``) and the stage key's settings
(``pipeline/run.py``) are all loops over :data:`OPTIONS`.
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Option:
    """One keyword option of ``calibrate``.

    name : the keyword. kind : ``str`` (then ``choices``), ``float``, ``int`` or ``bool``.
    choices : allowed values (``None`` among them is an alias the CLI does not show).
    lo, hi : allowed range of a number, ``lo < v`` when ``lo_open`` else ``lo <= v``, and ``v <= hi``.
    flag : the CLI spelling (``None``: library only); a bool's flag switches the default
        (``--no-tdoa-s`` sets ``use_tdoa_s`` False). help : the CLI / docs text.
    """
    name: str
    kind: type
    help: str = ""
    choices: tuple = ()
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    flag: str | None = None

    @property
    def default(self) -> Any:
        """The default of ``calibrate_features``' keyword."""
        return defaults()[self.name]

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
    Option("method", str, "estimator: hybrid (ours) or wang (baseline, no TDOA-S)", choices=("hybrid", "wang"),
           flag="--method"),
    Option("use_tdoa_s", bool, "ignore TDOA-S (Wang et al.'s measurement set)", flag="--no-tdoa-s"),
    Option("emission_sigma", float, "prior std (s) of emission-interval errors to estimate; 0 = off", lo=0.0,
           hi=10.0, flag="--emission-sigma"),
    Option("loss", str, "robust loss on TDOA residuals: cauchy, huber or linear",
           choices=("cauchy", "huber", "linear", None), flag="--loss"),
    Option("outlier_threshold", float, "flag and drop measurements (TDOA, DOA, odometry) whose normalised residual "
           "exceeds this many sigmas (or the Bonferroni level, if larger)", lo=1.0, hi=1e3,
           flag="--outlier-threshold"),
    Option("noise", str, "weights: auto (re-estimate the frontend's own noise figures from the residuals), meta "
           "(meta.json's sigmas as they are) or estimate", choices=("auto", "meta", "estimate"), flag="--noise"),
    Option("array_noise", bool, "when noise figures are re-estimated: also one figure per measurement type and "
           "array where the data allow it (an array noisier than the rest is down-weighted instead of distorting "
           "the others)", flag="--array-noise"),
    Option("robust_k", float, "robust scale, in units of each type's sigma", lo=0.0, lo_open=True),
    Option("max_iter", int, "iterations of each Levenberg-Marquardt solve", lo=1),
    Option("outputs", str, "all, or solution (the solve only)", choices=("all", "solution")),
)
OPTION = {o.name: o for o in OPTIONS}


def defaults() -> dict[str, Any]:
    """{keyword: default} of ``calibrate_features`` (the declaration of the defaults)."""
    from .calibrate import calibrate_features

    return {n: p.default for n, p in inspect.signature(calibrate_features).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY}


def cli_options() -> tuple[Option, ...]:
    """The options ``calib estimate`` and ``calib run`` take, in --help order."""
    return tuple(o for o in OPTIONS if o.flag)


def validate_options(**options: Any) -> None:
    """Raise ValueError with a clear message for any option of ``calibrate_features`` out of range.

    The one place the estimator options are checked (the CLI and ``pipeline.run`` call it before reading
    any data): NaN, infinities and negative values are refused, never silently used. Unknown keywords
    raise TypeError; keywords without declared constraints (``init_state``, ``problem``) pass.
    """
    known = defaults()
    for name, value in options.items():
        if name not in known:
            raise TypeError(f"unknown estimator option {name!r}")
        if name in OPTION:
            OPTION[name].check(value)
