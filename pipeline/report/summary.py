"""The report of a calibration: PNG plots and a markdown summary (``calib run`` writes OUT/report/).

``make_report(directory, features, calib, truth=None, diagnostics_dir=None)`` writes, atomically:

- ``scene_3d.png``: arrays as axis triads (x red, y green, z blue), sources, odometry path, truth
  overlaid when given, 1-σ position ellipsoids scaled up by the factor written in the legend;
- ``residuals.png``: one histogram per measurement type in natural units (µs, deg, cm) with the σ the
  estimator weighted it with marked and the Gaussian (Rayleigh for DOA angles) the model expects;
- ``detections.png``: the frontend's detection timeline (copied from diagnostics/ when present);
- ``summary.md``: arrays table, metrics vs truth, residuals, outliers, convergence, timings, links;
- ``metrics.json`` (only with truth): ``pipeline.report.evaluate.evaluate`` of the calibration.

Everything is computed from the files' contents (features + calibration), so a report made after a
skipped estimate is the same as one made right after it. Residuals and covariances come from the
estimator's own factors at the estimate (``estimator.solver.linearise``).
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

from calib.estimator import KINDS, LINE_COLUMN, position_covariances, rebuild, residuals

from calib.tables import METRIC_ROWS, extra_array_params, extra_param_cells
from calib.pipeline.formats.io import atomic_dir, dumps_json



def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ----------------------------------------------------------------------------------------------- plots
def _nice_scale(x):
    """Smallest 1, 2, 5 × 10^n that is ≥ x (and ≥ 1)."""
    if not np.isfinite(x) or x <= 1:
        return 1
    e = 10 ** math.floor(math.log10(x))
    return int(next(m * e for m in (1, 2, 5, 10) if m * e >= x))


def _rotations(df):
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(df[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True).as_matrix()


AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")  # an array's x, y, z axes
TRIAD = 0.08            # axis triad length, as a fraction of the scene's extent
ELLIPSOID_SHARE = 0.03  # the largest array 1-σ semi-axis is drawn at about this fraction of the extent


def plot_scene(path, calib, features, truth=None, cov_arrays=None, cov_sources=None):
    """3D view and top view (x-y) of the calibrated scene in the reference array's frame.

    cov_arrays (N, 3, 3), cov_sources (K, 3, 3): 1-σ position covariances (m²), drawn as ellipsoids /
    ellipses magnified by a round factor so that they are visible."""
    plt = _plt()
    sc = _scene_points(calib, features, truth)
    scale, sd_max = _ellipsoid_scale(cov_arrays, sc["extent"])
    fig = plt.figure(figsize=(15, 7.2))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    for i in range(len(sc["X"])):
        _draw_array(ax, ax2, sc, i, None if cov_arrays is None else cov_arrays[i], scale)
    _draw_sources(ax, ax2, sc, cov_sources, scale)
    ax2.legend(handles=_scene_legend(sc, scale, sd_max, cov_sources is not None), loc="upper left",
               bbox_to_anchor=(1.02, 1.0), fontsize=9, frameon=False)
    _finish_scene_axes(ax, ax2, sc)
    fig.suptitle(_scene_title(calib, truth), fontsize=13)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _scene_points(calib, features, truth):
    """Everything the scene plot draws, in the reference frame: arrays X (N,3), R (N,3,3), sources S,
    odometry O (anchored at the first source), truth tA/tR/tS (or None), extent (m), triad length L."""
    arr = calib["arrays"].reset_index(drop=True)
    X, R = arr[["x", "y", "z"]].to_numpy(float), _rotations(arr)
    src = calib.get("sources")
    S = src[["x", "y", "z"]].to_numpy(float) if src is not None else np.zeros((0, 3))
    odo = features["events"][["odom_x", "odom_y", "odom_z"]].to_numpy(float)
    known = np.flatnonzero(np.isfinite(S).all(axis=1))   # (a diverged solve's sources are unknown: NaN)
    O = odo - odo[known[0]] + S[known[0]] if len(known) else odo - odo[0]  # relative: anchored at a source
    tA = tR = tS = None
    if truth is not None:
        ta = truth["arrays"].set_index("array").reindex(arr["array"])
        tA = ta[["x", "y", "z"]].to_numpy(float)
        tR = np.full((len(ta), 3, 3), np.nan)
        okq = np.all(np.isfinite(ta[["qw", "qx", "qy", "qz"]].to_numpy(float)), axis=1)
        if okq.any():
            tR[okq] = _rotations(ta[okq])
        if truth.get("sources") is not None:
            tS = truth["sources"][["x", "y", "z"]].to_numpy(float)
    pts = [X, S, O] + ([tA[np.all(np.isfinite(tA), axis=1)]] if tA is not None else []) + \
          ([tS] if tS is not None else [])
    allp = np.vstack([q for q in pts if len(q)])
    allp = allp[np.isfinite(allp).all(axis=1)]
    lo, hi = allp.min(0), allp.max(0)
    extent = float(max(np.max(hi - lo), 0.5))
    return {"names": list(arr["array"]), "X": X, "R": R, "S": S, "events": None if src is None else
            src["event"].to_numpy(int), "O": O, "tA": tA, "tR": tR, "tS": tS, "lo": lo, "hi": hi,
            "extent": extent, "L": TRIAD * extent}


def _ellipsoid_scale(cov_arrays, extent):
    """(magnification, largest array 1-σ in m or NaN): a 1, 2, 5 × 10^n factor for the ellipsoids."""
    if cov_arrays is None:
        return 1, np.nan
    ev = [np.linalg.eigvalsh(c) for c in cov_arrays if np.all(np.isfinite(c))]
    if not ev:
        return 1, np.nan
    sd_max = math.sqrt(max(float(np.max(e)) for e in ev))
    return _nice_scale(ELLIPSOID_SHARE * extent / max(sd_max, 1e-12)), sd_max


def _triad(ax, ax2, origin, R, L, **style):
    """An array's axes as three coloured segments in both views."""
    for k in range(3):
        seg = np.c_[origin, origin + L * R[:, k]]
        ax.plot(*seg, color=AXIS_COLOURS[k], **style)
        ax2.plot(*seg[:2], color=AXIS_COLOURS[k], **style)


def _draw_array(ax, ax2, sc, i, cov, scale):
    """Array ``i``: axis triad, name, truth (circle, dotted axes, error line), 1-σ ellipsoid."""
    X, L, tA = sc["X"][i], sc["L"], sc["tA"]
    _triad(ax, ax2, X, sc["R"][i], L, lw=2.2)
    if tA is not None and np.all(np.isfinite(tA[i])):
        ax.plot(*np.c_[X, tA[i]], color="k", lw=0.8)  # error vector estimate → truth
        ax2.plot(*np.c_[X, tA[i]][:2], color="k", lw=0.8)
        ax.scatter(*tA[i], s=70, facecolors="none", edgecolors="k", lw=1.2)
        ax2.scatter(*tA[i][:2], s=90, facecolors="none", edgecolors="k", lw=1.2, zorder=4)
        if np.all(np.isfinite(sc["tR"][i])):
            _triad(ax, ax2, tA[i], sc["tR"][i], L, lw=1, ls=":", alpha=0.8)
    ax.scatter(*X, color="k", s=14)
    ax.text(*(X + 0.35 * L), sc["names"][i], fontsize=11, weight="bold")
    ax2.scatter(*X[:2], color="k", s=14, zorder=5)
    ax2.annotate(sc["names"][i], X[:2], xytext=(6, 6), textcoords="offset points", fontsize=11, weight="bold")
    if cov is not None and np.all(np.isfinite(cov)):
        u, v = np.mgrid[0:2 * np.pi:16j, 0:np.pi:9j]
        sphere = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1)
        w, V = np.linalg.eigh(cov)
        E = X + scale * (sphere * np.sqrt(np.maximum(w, 0))) @ V.T
        ax.plot_wireframe(E[..., 0], E[..., 1], E[..., 2], color="tab:purple", lw=0.5, alpha=0.6)
        _ellipse(ax2, X[:2], scale * cov[:2, :2] * scale, "tab:purple")


def _draw_sources(ax, ax2, sc, cov_sources, scale):
    """Estimated sources (path), their 1-σ ellipses, the odometry path and the true sources."""
    S = sc["S"]
    if len(S):
        ax.plot(*S.T, "o-", color="tab:orange", ms=4, lw=1)
        ax2.plot(*S[:, :2].T, "o-", color="tab:orange", ms=4, lw=1)
        for j in (0, len(S) - 1):
            ax2.annotate(f"event {sc['events'][j]}", S[j, :2], xytext=(5, -12), textcoords="offset points",
                         fontsize=9, color="tab:orange")
        for j in range(len(S) if cov_sources is not None else 0):
            if np.all(np.isfinite(cov_sources[j])):
                _ellipse(ax2, S[j, :2], scale * cov_sources[j][:2, :2] * scale, "tab:orange", lw=0.7, alpha=0.5)
    ax.plot(*sc["O"].T, "--", color="0.45", lw=1)
    ax2.plot(*sc["O"][:, :2].T, "--", color="0.45", lw=1)
    if sc["tS"] is not None:
        ax.scatter(*sc["tS"].T, marker="x", color="k", s=22, lw=1)
        ax2.scatter(*sc["tS"][:, :2].T, marker="x", color="k", s=22, lw=1)


def _scene_legend(sc, scale, sd_max, with_source_cov):
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=c, lw=2.2, label=f"array {a} axis") for c, a in zip(AXIS_COLOURS, "xyz")]
    handles += [Line2D([], [], color="tab:orange", marker="o", ms=4, lw=1, label="sources (estimate)"),
                Line2D([], [], color="0.45", ls="--", label="odometry path (anchored at first source)")]
    if sc["tA"] is not None:
        handles += [Line2D([], [], marker="o", mfc="none", mec="k", ls="",
                           label="arrays (truth, dotted axes; line = error)")]
    if sc["tS"] is not None:
        handles += [Line2D([], [], marker="x", color="k", ls="", label="sources (truth)")]
    if np.isfinite(sd_max):
        handles += [Line2D([], [], color="tab:purple", lw=1,
                           label=f"1-σ array position ellipsoids ×{scale} (largest σ {100 * sd_max:.1f} cm)")]
        if with_source_cov and len(sc["S"]):
            handles += [Line2D([], [], color="tab:orange", lw=0.7, alpha=0.6,
                               label=f"1-σ source ellipses (x-y) ×{scale}")]
    return handles


def _finish_scene_axes(ax, ax2, sc):
    mid = 0.5 * (sc["lo"] + sc["hi"])
    half = 0.5 * sc["extent"] * 1.05
    ax.set(xlim=(mid[0] - half, mid[0] + half), ylim=(mid[1] - half, mid[1] + half),
           zlim=(mid[2] - half, mid[2] + half), xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=25, azim=-60)
    ax.set_title("3D view (reference array's frame)")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set(xlabel="x (m)", ylabel="y (m)", title="Top view (x-y)")
    ax2.grid(alpha=0.3)


def _ellipse(ax, c, cov2, color, lw=1.0, alpha=0.8):
    """The 1-σ ellipse of a 2×2 covariance ``cov2`` centred at ``c``."""
    from matplotlib.patches import Ellipse

    w, V = np.linalg.eigh(cov2)
    w = np.sqrt(np.maximum(w, 0))
    ang = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
    ax.add_patch(Ellipse(c, 2 * w[1], 2 * w[0], angle=ang, fill=False, color=color, lw=lw, alpha=alpha))


def _scene_title(calib, truth):
    n = len(calib["arrays"])
    k = len(calib["sources"]) if calib.get("sources") is not None else 0
    return f"Calibrated scene: {n} arrays, {k} sources" + (" — estimate vs truth" if truth is not None else "")


def plot_residuals(path, res):
    """One histogram per measurement type, natural units, the σ used marked, outliers counted; the curve
    is the density the model expects, each row with its own σ (:func:`expected_density`)."""
    plt = _plt()
    kinds = list(res)
    fig, axes = plt.subplots(1, max(len(kinds), 1), figsize=(4.4 * max(len(kinds), 1), 4.6), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        d = res[kind]
        v, o = d["values"], d["outlier"]
        inl, row_sig = v[~o], _row_sigma(d)[~o]
        sig = float(np.median(row_sig)) if row_sig.size else d["sigma"]
        data_hi = 1.15 * float(np.abs(inl).max()) if inl.size and np.abs(inl).max() > 0 else sig
        # show the σ's range unless it would squash the data into a bin or two
        show_sig = sig <= 1.5 * data_hi
        hi = max(data_hi, 1.1 * sig) if show_sig else data_hi
        lo_ = 0.0 if d["dist"] == "rayleigh" else -hi
        bins = np.linspace(lo_, hi, 25)
        ax.hist(np.clip(inl, lo_, hi), bins=bins, color="tab:blue", alpha=0.75, label=f"used ({inl.size})")
        if o.any():
            ax.hist(np.clip(v[o], lo_, hi), bins=bins, color="tab:red", alpha=0.85,
                    label=f"outliers ({int(o.sum())}, clipped)")
        if show_sig:
            xs = np.linspace(lo_, hi, 300)
            for m_ in ((sig,) if d["dist"] == "rayleigh" else (-sig, sig)):
                ax.axvline(m_, color="k", ls="--", lw=1)
            ax.plot(xs, expected_density(xs, row_sig, d["dist"]) * inl.size * (bins[1] - bins[0]), color="k",
                    lw=1.2, label=_expected_label(d, row_sig))
        else:
            rms_ = float(np.sqrt(np.mean(inl ** 2))) if inl.size else float("nan")
            ax.text(0.02, 0.97, f"σ used = {sig:.3g} {d['unit']} (off scale):\n"
                    f"the RMS is {sig / rms_:.1f}× smaller", transform=ax.transAxes, va="top",
                    fontsize=8, bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"})
        rms = float(np.sqrt(np.mean(inl ** 2))) if inl.size else float("nan")
        ax.set_title(f"{KINDS[kind].title}: RMS {rms:.3g} {d['unit']}")
        ax.set_xlabel(KINDS[kind].label)
        ax.set_ylabel("count")
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)
    fig.suptitle("Residuals at the estimate (dashed: the σ the estimator weighted with, median over rows)",
                 fontsize=12)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _row_sigma(d):
    """(m,) the σ each of a type's values was weighted with (the type's σ for all when not given)."""
    return np.broadcast_to(np.asarray(d.get("row_sigma", d["sigma"]), float), d["values"].shape)


def expected_density(x, row_sigma, dist):
    """The density of one residual drawn from a random row (rows of 1-σ ``row_sigma`` (m,), > 0): the mean
    of their N(0, σ) — or, for ``dist == "rayleigh"`` (DOA angles, σ per tangent axis), Rayleigh(σ) —
    densities at ``x`` (n,). Returns (n,); one σ for all rows gives the plain density."""
    s = np.unique(np.asarray(row_sigma, float), return_counts=True)
    sig, w = s[0][:, None], s[1][:, None] / max(s[1].sum(), 1)
    z = np.asarray(x, float)[None, :] / sig
    pdf = z / sig * np.exp(-0.5 * z * z) if dist == "rayleigh" else np.exp(-0.5 * z * z) / (sig * np.sqrt(2 * np.pi))
    return (w * pdf).sum(axis=0)


def _expected_label(d, row_sig):
    """Legend text of the expected density: its σ, or the rows' median and range when they differ."""
    sig = _sigma_text(d, row_sig, one="= ")
    return f"expected (Rayleigh, σ {sig})" if d["dist"] == "rayleigh" else f"expected N(0, σ), σ {sig}"


def _sigma_text(d, row_sig, one=""):
    """``1.2 µs`` (after ``one``), or ``per row: median 1.2, 0.8–3.1 µs`` when the rows were weighted
    differently."""
    unit = f" {d['unit']}" + ("/axis" if d["dist"] == "rayleigh" else "")
    lo, med, hi = np.percentile(row_sig, [0, 50, 100]) if row_sig.size else (d["sigma"],) * 3
    if np.isclose(lo, hi, rtol=1e-6):
        return f"{one}{med:.3g}{unit}"
    return f"per row: median {med:.3g}, {lo:.3g}–{hi:.3g}{unit}"


# ----------------------------------------------------------------------------------------------- summary
def _fmt(v, fmt, scale=1.0):
    try:
        v = float(v) * scale
    except (TypeError, ValueError):
        return "—"
    return format(v, fmt) if math.isfinite(v) else "—"


def arrays_markdown(arrays):
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_quat(arrays[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True).as_rotvec()
    extra = [(a, c) for a in extra_array_params() for c in a.columns]   # registered beyond the built-in ones
    lines = ["| array | x (m) | y (m) | z (m) | rotation (deg) about axis | offset (ms) | drift (ppm) "
             "| ±pos (cm) | ±rot (deg) | ±offset (µs) | ±drift (ppm) |" + "".join(f" {c} ({a.unit}) |" for a, c in extra),
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(extra)]
    for k, r in arrays.reset_index(drop=True).iterrows():
        ang = np.linalg.norm(rv[k])
        ax = rv[k] / ang if ang > 0 else np.array([0.0, 0.0, 1.0])
        pos_sd = math.sqrt(sum(float(r.get(f"{c}_std", np.nan)) ** 2 for c in "xyz"))
        rot_sd = math.degrees(math.sqrt(sum(float(r.get(f"r{c}_std", np.nan)) ** 2 for c in "xyz")))
        lines.append(f"| {r['array']} | {r['x']:.3f} | {r['y']:.3f} | {r['z']:.3f} | "
                     f"{np.degrees(ang):.1f} about ({ax[0]:.2f}, {ax[1]:.2f}, {ax[2]:.2f}) | "
                     f"{_fmt(r['offset'], '.3f', 1e3)} | {_fmt(r['drift'], '.2f', 1e6)} | {_fmt(pos_sd, '.2f', 100)} | "
                     f"{_fmt(rot_sd, '.2f')} | {_fmt(r.get('offset_std'), '.1f', 1e6)} | "
                     f"{_fmt(r.get('drift_std'), '.3f', 1e6)} |"
                     + "".join(f" {c} |" for a in extra_array_params() for c in extra_param_cells(r, a)))
    return "\n".join(lines)


def metrics_markdown(metrics):

    lines = ["| metric | value | unit |", "|---|---:|---|"]
    for key, label, scale, unit in METRIC_ROWS:
        lines.append(f"| {label} | {_fmt(metrics.get(key), '.3f', scale)} | {unit} |")
    lines += ["", "| array | position (cm) | geodesic (deg) | paper metric (deg) | axis (deg) | offset (µs) | "
              "drift (ppm) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in metrics.get("per_array", []):
        lines.append(f"| {r['array']} | {_fmt(r['position_m'], '.2f', 100)} | {_fmt(r['geodesic_deg'], '.2f')} | "
                     f"{_fmt(r['paper_deg'], '.2f')} | {_fmt(r.get('axis_deg'), '.2f')} | "
                     f"{_fmt(r['offset_s'], '.1f', 1e6)} | {_fmt(r['drift'], '.3f', 1e6)} |")
    return "\n".join(lines)


def _outlier_lines(features, outliers):
    out = []
    for o in outliers:
        spec = KINDS.get(o["type"])
        source = spec.source if spec is not None else o["type"]   # (cone rows are in doa.csv)
        df = features.get(source)
        line = int(o["line"])
        what = f"event {o['event']}, array {o['array']}" if o.get("array") else \
            (f"step to event {o['event']}" if o.get("event") is not None else "")
        hit = None if df is None else (df[df[LINE_COLUMN] == line] if LINE_COLUMN in df else df.iloc[line - 2:line - 1])
        if hit is not None and len(hit):
            r = hit.iloc[0]
            if o["type"] == "tdoa_m":
                what = f"event {r['event']}, array {r['array']}"
            elif o["type"] == "tdoa_s":
                what = f"array {r['array']}, events {r['from_event']}→{r['to_event']}"
        size = f"{o['residual_us']:+.0f} µs" if "residual_us" in o else f"{o.get('residual', float('nan')):.3g} " \
                                                                       f"{o.get('unit', '')}"
        where = f"step {line}" if spec is not None and not spec.per_array else f"features/{source}.csv line {line}"
        out.append(f"- {o['type']} ({what}), {where}: residual {size} = "
                   f"{o['residual_sigma']:+.1f} σ — excluded from the final solve")
    return out


DISTRUST_LABEL = {"nlos": "reflection only (NLOS: line of sight blocked)", "absurd": "absurd TDOA"}


def verdict_markdown(verdict):
    """The summary's first lines: title with the verdict's status, then its reasons (report.json ``verdict``)."""
    if not verdict:
        return ["# Calibration report — verdict: unknown (calibration written before verdicts existed)", ""]
    L = [f"# Calibration report — verdict: {str(verdict.get('status', '?')).upper()}", ""]
    if verdict.get("flagged_arrays"):
        L += [f"Flagged arrays (inconsistent with the others; their pose is unreliable): "
              f"**{', '.join(verdict['flagged_arrays'])}**", ""]
    L += [f"- {r}" for r in verdict.get("reasons") or []]
    L += [""] if verdict.get("reasons") else []
    if verdict.get("distrusted"):
        L += ["| array | not trusted | events | |", "|---|---|---|---|"]
        L += [f"| {d['array']} | {DISTRUST_LABEL.get(d['reason'], d['reason'])} | "
              f"{', '.join(map(str, d['events'])) or 'most'} | {'taken out' if d['taken_out'] else 'kept'} |"
              for d in verdict["distrusted"]]
        L += ["", "(detections.png marks the NLOS arrivals ▼ red and the other doubted ones ▼ orange.)", ""]
    return L


def _row_weight_lines(rep):
    """Notes under the residual table on why a type's rows have different σ: DOA rows weighted by their
    own sigmas (report.json ``sigmas.doa_row_scale``), TDOA rows by their arrays' arrival sigmas
    (``sigmas.arrival_scale``), arrays by their own variance components
    (``sigmas.per_array_factor``)."""
    sig = rep.get("sigmas") or {}
    out = []
    rows = sig.get("doa_row_scale")
    if rows:
        out.append(f"- DOA rows weighted by their own sigmas (doa.csv `sigma_deg`, shrunk halfway to the type's): "
                   f"{rows['rows']} rows at {rows['min']:.2f}–{rows['max']:.2f}× the type's σ "
                   f"(median {rows['median']:.2f}).")
    arrival = sig.get("arrival_scale")
    if arrival:
        out.append("- TDOA rows weighted by their arrays' own arrival sigmas (meta.json `sigma_arrival_per_array`, "
                   "× the pooled one): " + ", ".join(f"{a} {v:.2f}" for a, v in arrival.items()) + ".")
    for kind, arrays in (sig.get("per_array_factor") or {}).items():
        if arrays:
            out.append(f"- {KINDS[kind].title if kind in KINDS else kind}: arrays with a σ of their own (× the type's): "
                       + ", ".join(f"{a} {v:.2f}" for a, v in arrays.items()) + ".")
    return ["", *out] if out else []


def summary_markdown(features, calib, res, metrics, diag, images):
    rep = calib.get("report") or {}
    L = verdict_markdown(rep.get("verdict"))
    L += [f"Reference array **{features['meta']['reference_array']}** (its frame is the world frame); "
          f"{len(calib['arrays'])} arrays, {len(features['events'])} events, method `{rep.get('method', '?')}`, "
          f"calib {(rep.get('software') or {}).get('version', '?')}.", ""]
    L += ["## Calibrated arrays", "",
          "Position in the reference array's frame, rotation (array frame → reference frame) as angle and "
          "axis, clock offset at the first event and drift relative to the emitter's clock; ± columns are "
          "1-σ from the estimator's covariance (position: norm over x, y, z).", "",
          arrays_markdown(calib["arrays"]), ""]
    und = rep.get("undetermined") or []
    if und:   # what the data do not determine (not estimated, NaN std): one line per array
        by = {}
        for u in und:
            by.setdefault(u["array"], []).append(u["parameter"])
        L += ["Not determined by the data (not estimated, no σ; the rest is): "
              + "; ".join(f"{a}: {', '.join(v)}" for a, v in by.items()) + ".", ""]
    L += clock_lines(rep.get("clock") or {}, rep.get("setup"), calib["arrays"])
    L += speed_lines(rep.get("speed_of_sound"))
    if metrics is not None:
        L += ["## Evaluation against ground truth", "", metrics_markdown(metrics), ""]
    L += ["## Scene", "", f"![scene]({images['scene']})", ""]
    source = (rep.get("sigmas") or {}).get("source", "meta")
    L += ["## Residuals", "", f"| type | n | RMS | σ used ({source}) |", "|---|---:|---:|---:|"]
    for kind, d in res.items():
        v = d["values"][~d["outlier"]]
        rms = float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")
        L.append(f"| {KINDS[kind].title} | {v.size} | {rms:.3g} {d['unit']} | {_sigma_text(d, _row_sigma(d)[~d['outlier']])} |")
    L += _row_weight_lines(rep)
    if res:
        L += ["", f"![residuals]({images['residuals']})", ""]
    outl = rep.get("outliers") or []
    L += ["## Outliers", ""] + (_outlier_lines(features, outl) if outl else ["None flagged."]) + [""]
    it = rep.get("iterations") or {}
    cost = rep.get("cost") or {}
    L += ["## Convergence", "",
          f"- converged: **{rep.get('converged', '?')}** ({rep.get('reason', '?')}); iterations: robust pass "
          f"{it.get('robust', '?')}, final pass {it.get('final', '?')}",
          "- cost by stage: " + ", ".join(f"{k} {_fmt(v, '.4g')}" for k, v in cost.items()),
          f"- χ²/dof at the estimate: {_fmt(rep.get('chi2_per_dof'), '.3f')} (≈ 1 when the σ used are right)",
          f"- drift reference: {rep.get('drift_reference', '?')}", ""]
    if diag is not None:
        L += ["## Detections", ""]
        for name, a in (diag.get("arrays") or {}).items():
            det = a.get("detections", [])
            n_sp = len(a.get("spurious", []))
            miss = a.get("missed_events", [])
            L.append(f"- {name}: {len(det) - n_sp} matched, missed events {miss or 'none'}, {n_sp} spurious"
                     + "".join(f"; warning: {w}" for w in a.get("warnings", [])))
        L += ["", f"![detections]({images['detections']})", ""] if images.get("detections") else [""]
    L += ["## Timings", ""]
    if diag is not None and diag.get("elapsed_s") is not None:
        rec = diag.get("recording_duration_s")
        L.append(f"- features: {diag['elapsed_s']:.2f} s" + (f" for {rec:.1f} s of recording" if rec else ""))
    for k, v in (rep.get("timings_s") or {}).items():
        L.append(f"- estimator {k}: {v:.3f} s")
    return "\n".join(L) + "\n"


def speed_lines(speed):
    """The speed of sound the calibration used (report.json ``speed_of_sound``): solved, with its 1-σ and the
    declared value, or as declared (and why: the data did not tell it apart, or it was fixed — then what the data
    ask for when its check is significant)."""
    if not speed:
        return []
    c, c0 = speed.get("value_m_s"), speed.get("declared_m_s")
    if speed.get("estimated"):
        return [f"Speed of sound **{c:.1f} ± {speed['std_m_s']:.1f} m/s**, solved from the data "
                f"({100 * (c / c0 - 1):+.1f} % against the declared {c0:.1f} m/s: the arrays' positions use it).", ""]
    test, check = speed.get("test"), speed.get("check") or {}
    if not test and check.get("significant"):   # c fixed, the data's checked (estimator/soundspeed.speed_check)
        return [f"Speed of sound {c:.1f} m/s as declared (fixed by option), but the data ask for "
                f"{check['fitted_m_s']:.1f} ± {check['std_relative'] * c0:.1f} m/s ({100 * check['relative']:+.1f} %, "
                f"{check['z']:.1f}σ): see the verdict.", ""]
    why = "fixed by option" if not test else (
        f"the data put it at {test['fitted_m_s']:.1f} ± {test['std_relative'] * c0:.1f} m/s, not told apart"
        if test.get("std_relative") else "not testable on these data")
    return [f"Speed of sound {c:.1f} m/s as declared ({why}).", ""]


def rep_clock(calib):
    """report.json ``clock`` of a calibration ({} without clock models)."""
    return (calib.get("report") or {}).get("clock") or {}


def step_marks(clock, diag):
    """{array: [(time on its clock, label)]}: each clock step midway between the detections of the two events
    it lies between (steps whose events were not both detected are left out)."""
    out = {}
    for name, e in (clock.get("arrays") or {}).items():
        det = {d["event"]: d["time"] for d in ((diag.get("arrays") or {}).get(name) or {}).get("detections", [])
               if d.get("event") is not None}
        for s in e.get("steps") or []:
            a, b = det.get(s["after_event"]), det.get(s["before_event"])
            if a is not None and b is not None:
                out.setdefault(name, []).append((0.5 * (a + b), f"{s['size'] * 1e3:+.2f} ms step"))
    return out


def clock_lines(clock, setup=(), arrays=None):
    """summary.md's clock section: one line per finding (steps, drift models, wrong rates, emission times), the
    set-up check's notes on sample rates (report.json ``setup``: a clock faster than a crystal runs, taken at
    its measured rate; a wrong header is a verdict reason already), and for each array taken at another rate
    than its header's its clock's rate as calibrated (:func:`rate_lines`; ``arrays``: arrays.csv's frame)."""
    f = (clock.get("findings") or []) + [x["text"] for x in setup or ()
                                         if x.get("status") == "note" and x.get("check") == "sample rate"]
    f += rate_lines(clock, arrays)
    if not f:
        return []
    return ["## Clocks", "", "Each array's clock model, chosen by the evidence (docs/method.md \"Clock models\"):",
            ""] + [f"- {x}" for x in f] + [""]


def rate_lines(clock, arrays):
    """One line per array whose samples were taken at another rate than its WAV header's (report.json
    ``clock.arrays``: ``sample_rate``, ``header_sample_rate``): the rate its clock runs at against the emitter's,
    sample_rate × (1 + drift), to the digits its 1-σ (sample_rate × drift_std) gives, and that drift on its
    header's time base (r(1 + δ) − 1, what a reader trusting the header sees)."""
    if arrays is None:
        return []
    rows = {str(r["array"]): r for _, r in arrays.iterrows()}
    out = []
    for name, e in (clock.get("arrays") or {}).items():
        fs, header, row = e.get("sample_rate"), e.get("header_sample_rate"), rows.get(name)
        if not (fs and header and row is not None and np.isfinite(row["drift"])):
            continue
        rate, sd = fs * (1.0 + float(row["drift"])), fs * float(row.get("drift_std", np.nan))
        ppm, sd_ppm = 1e6 * (rate / header - 1.0), 1e6 * sd / header
        pm = (lambda v: f" ± {v:.{_digits(v)}f}") if np.isfinite(sd) and sd > 0 else (lambda v: "")
        out.append(f"{name}: its samples taken at {fs} Hz (WAV header: {header} Hz); its clock runs at "
                   f"{rate:.{_digits(sd)}f}{pm(sd)} Hz against the emitter's, {ppm:+.{_digits(sd_ppm)}f}{pm(sd_ppm)} "
                   f"ppm on its header's rate (its offset and drift are relative to {fs} Hz)")
    return out


def _digits(sd, default=3):
    """Decimals that show a value to its 1-σ ``sd``'s second significant digit (``default`` when unknown)."""
    return max(0, 1 - int(np.floor(np.log10(sd)))) if np.isfinite(sd) and sd > 0 else default


# ----------------------------------------------------------------------------------------------- driver
def make_report(directory, features, calib, truth=None, diagnostics_dir=None, progress=None):
    """Write the report folder atomically. Returns the evaluation metrics (dict) when ``truth`` is given."""
    step = (lambda k, msg: progress(k, 5, msg)) if progress else (lambda k, msg: None)
    metrics = None
    if truth is not None:
        from calib.pipeline.formats.calibration_json import reference_offset
        from calib.pipeline.report.evaluate import evaluate, rate_scales

        if rate_scales(calib) and calib.get("reference_offset") is None:   # (an in-memory calibration)
            tau = reference_offset(features["meta"], calib["arrays"], calib.get("sources"), features["events"])[0]
            calib = {**calib, "reference_offset": tau}
        metrics = evaluate(calib, truth)
    step(0, "residuals")
    model = rebuild(features, calib)
    res = residuals(model) if model is not None else {}
    cov_a = cov_s = None
    if model is not None:
        cov_a, cov_s = position_covariances(model)
    diag = None
    if diagnostics_dir is not None and (Path(diagnostics_dir) / "diagnostics.json").is_file():
        diag = json.loads((Path(diagnostics_dir) / "diagnostics.json").read_text())
    images = {"scene": "scene_3d.png", "residuals": "residuals.png"}
    with atomic_dir(directory) as tmp:
        step(1, "scene plot")
        plot_scene(tmp / "scene_3d.png", calib, features, truth, cov_a, cov_s)
        step(2, "residual plot")
        if res:
            plot_residuals(tmp / "residuals.png", res)
        step(3, "detections")
        src_png = Path(diagnostics_dir) / "detections.png" if diagnostics_dir is not None else None
        marks = step_marks(rep_clock(calib), diag) if diag is not None else {}
        if marks:   # the clock steps the estimator found, on each array's detection row (redrawn)
            from calib.frontend import plot_detections

            plot_detections(tmp / "detections.png", diag, marks=marks)
            images["detections"] = "detections.png"
        elif src_png is not None and src_png.is_file():
            shutil.copyfile(src_png, tmp / "detections.png")
            images["detections"] = "detections.png"
        elif diag is not None:
            from calib.frontend import plot_detections  # the frontend owns its timeline plot

            plot_detections(tmp / "detections.png", diag)
            images["detections"] = "detections.png"
        step(4, "summary")
        if metrics is not None:
            (tmp / "metrics.json").write_text(dumps_json(metrics, indent=2) + "\n")
        (tmp / "summary.md").write_text(summary_markdown(features, calib, res, metrics, diag, images))
    step(5, "done")
    return metrics
