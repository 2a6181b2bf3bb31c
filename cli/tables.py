"""Rich tables shared by the commands (one place for how arrays and metrics are shown)."""
from __future__ import annotations

import math

import numpy as np
from rich.console import Console
from rich.table import Table

from calib.tables import METRIC_ROWS, extra_array_params, extra_param_cells  # (not report.evaluate: scipy.spatial)

out = Console()


def _f(v, fmt):
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def print_arrays(calib, console=None):
    """Table of calibrated arrays: position (m), orientation (rotation vector, deg), offset (ms), drift (ppm)."""
    from scipy.spatial.transform import Rotation  # here: `calib features` and `calib --help` need no scipy.spatial

    a = calib["arrays"]
    t = Table(title="Calibrated arrays: position m, rotation angle deg, offset ms, drift ppm, 1-σ cm / deg",
              padding=(0, 1), collapse_padding=True)
    extra = extra_array_params()   # registered per-array parameters beyond these: their own columns, SI
    for col in ("array", "x", "y", "z", "angle", "offset", "drift", "±pos", "±rot",
                *(f"{c} {a.unit}" for a in extra for c in a.columns)):
        t.add_column(col, justify="right")
    # rotation shown as its angle (the axis is in arrays.csv); keeps the table within 80 columns
    rv = np.rad2deg(Rotation.from_quat(a[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True).magnitude())
    for k, row in a.reset_index(drop=True).iterrows():
        pos_sd = math.sqrt(sum(row.get(f"{c}_std", float("nan")) ** 2 for c in "xyz")) * 100
        rot_sd = math.degrees(math.sqrt(sum(row.get(f"r{c}_std", float("nan")) ** 2 for c in "xyz")))
        t.add_row(str(row["array"]), _f(row["x"], ".3f"), _f(row["y"], ".3f"), _f(row["z"], ".3f"),
                  _f(rv[k], ".1f"), _f(row["offset"] * 1e3, ".3f"),
                  _f(row["drift"] * 1e6, ".2f"), _f(pos_sd, ".2f"), _f(rot_sd, ".2f"),
                  *(c for a in extra for c in extra_param_cells(row, a)))
    (console or out).print(t)


def print_metrics(metrics, console=None):
    """Table of evaluation metrics (and per-array errors)."""
    t = Table(title="Calibration vs ground truth")
    t.add_column("metric")
    t.add_column("value", justify="right")
    t.add_column("unit")
    for key, label, scale, unit in METRIC_ROWS:
        v = metrics.get(key, float("nan"))
        t.add_row(label, _f(v * scale if v is not None else v, ".3f"), unit)
    (console or out).print(t)
    pa = Table(title="Per array")
    rows = metrics.get("per_array", [])
    axis = any(np.isfinite(r.get("axis_deg", np.nan)) for r in rows)  # linear arrays / pairs: axis error
    for col in ("array", "position [cm]", "geodesic [deg]", "paper [deg]", *(("axis [deg]",) if axis else ()),
                "offset [µs]", "drift [ppm]"):
        pa.add_column(col, justify="right")
    for r in rows:
        pa.add_row(r["array"], _f(100 * r["position_m"], ".2f"), _f(r["geodesic_deg"], ".2f"),
                   _f(r["paper_deg"], ".2f"), *((_f(r.get("axis_deg", np.nan), ".2f"),) if axis else ()),
                   _f(1e6 * r["offset_s"], ".1f"), _f(1e6 * r["drift"], ".2f"))
    (console or out).print(pa)
    if metrics.get("clock"):
        print_clock_metrics(metrics["clock"], console)


def print_clock_metrics(clock, console=None):
    """Table of the recovered clock models against the true clocks (``evaluate``'s ``clock``)."""
    t = Table(title=f"Clocks: {clock['steps_found']}/{clock['steps_true']} true steps found, "
                    f"{clock['steps_placed']} in their interval, {clock['steps_size_ok']} with size within 3σ; "
                    f"{clock['false_steps']} false step(s), {clock['false_drift_models']} false drift model(s)")
    for col in ("array", "true steps [ms]", "found steps: interval, size error [µs] (σ)", "false", "drift model "
                "(true → found)", "rate ratio (true → found)", "max local-time error [µs]"):
        t.add_column(col, justify="right")
    for a in clock["per_array"]:
        found = ", ".join(f"{'ok' if s['placed'] else '?' if s['placed'] is None else 'misplaced'} {_f(1e6 * s['size_error_s'], '.1f')} "
                          f"({_f(s['size_error_sigma'], '.1f')}σ)" if s["found"] else "missed" for s in a["steps"])
        t.add_row(a["array"], ", ".join(f"{1e3 * s['size']:+.3f}" for s in a["steps"]) or "—", found or "—",
                  str(a["false_steps"]), f"{a['drift_model_true']} → {a['drift_model']}",
                  f"{a['rate_ratio_true']:.5f} → {_f(a['rate_ratio'], '.5f')}", _f(None if a["local_time_max_error_s"] is None else 1e6 * a["local_time_max_error_s"], ".1f"))
    (console or out).print(t)
