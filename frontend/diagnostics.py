"""The frontend's detection-timeline plot (``detections.png``); ``calib.pipeline.features`` writes it."""
from __future__ import annotations

import numpy as np



PLOT_POINTS = 4000   # envelope points per row of the detection plot


def _pool(env, rate, width=PLOT_POINTS):
    """Max-pool an envelope to about ``width`` points (peaks stay visible). Returns (t, y)."""
    k = max(1, len(env) // width)
    n = len(env) // k * k
    y = env[:n].reshape(-1, k).max(axis=1)
    return (np.arange(len(y)) * k + k / 2) / rate, y


def envelope_summary(env, rate, median=None):
    """What the detection plot draws of a matched-filter envelope: ``(t, y, median)``, the envelope max-pooled
    to about :data:`PLOT_POINTS` and the full envelope's median (its 0 dB). Kept instead of the envelope itself,
    which grows with the recording (2 h at 48 kHz: 126 MB per array). median : ``np.median(env)`` when known."""
    t, y = _pool(np.asarray(env), rate)
    return t, y, float(np.median(env) if median is None else median)


# margins of the detection plot, inches: tick labels + "dB" left, suptitle + first title on top, x label below,
# each row's title between rows
MARGIN_IN = {"left": 0.75, "right": 0.2, "top": 0.8, "bottom": 0.55, "between": 0.42}


def _fixed_margins(fig, n_rows):
    """Lay out ``n_rows`` stacked axes with the fixed margins of :data:`MARGIN_IN`."""
    w, h = fig.get_size_inches()
    m = MARGIN_IN
    row = (h - m["top"] - m["bottom"] - (n_rows - 1) * m["between"]) / n_rows
    fig.subplots_adjust(left=m["left"] / w, right=1 - m["right"] / w, top=1 - m["top"] / h,
                        bottom=m["bottom"] / h, hspace=m["between"] / row)


NLOS_COLOR, DOUBT_COLOR = "tab:red", "tab:orange"
STRONG_DOUBTS = ("nlos", "occluded", "weak_direct", "track", "redetected")   # marked on the timeline


def _mark_doubted(ax, a, top):
    """▼ above each arrival the estimator distrusts or may: red for NLOS (reflection-only: taken out by the
    estimator), orange for the other strong doubts (docs/frontend.md)."""
    for x in a.get("arrivals", []):
        flags = (x.get("flag") or "").split("+")
        if "nlos" in flags:
            color = NLOS_COLOR
        elif any(f in STRONG_DOUBTS for f in flags):
            color = DOUBT_COLOR
        else:
            continue
        ax.plot([x["time"]], [top * 1.13], "v", color=color, ms=5)


FIG_WIDTH_IN = 13.0
LABEL_CHAR_IN = 0.06   # width of a 7-point digit (inches), and the gap kept between two event labels
LABEL_GAP_IN = 0.05


def _legible(times, labels, t_max):
    """The (time, label) pairs of a row drawn without overlapping: left to right, a label only where it clears
    the last one drawn (a 3-minute session's 90 events fill every other slot; a 2-hour session's 3600 would
    cost ~0.4 ms of drawing each, ~15 s for 8 arrays, to print an unreadable smear). Returns a list."""
    s_per_in = t_max / (FIG_WIDTH_IN - MARGIN_IN["left"] - MARGIN_IN["right"])
    out, last = [], -np.inf
    for t, label in sorted(zip(times, labels)):
        half = 0.5 * len(label) * LABEL_CHAR_IN * s_per_in
        if t - half >= last:
            out.append((t, label))
            last = t + half + LABEL_GAP_IN * s_per_in
    return out


def plot_detections(path, diag, marks=None):
    """Detection timeline, one row per array on its own clock: matched-filter envelope (dB re. its median),
    matched detections (green, event id where it fits beside the previous one), spurious ones (red ×), missed
    events at their predicted time (grey dashed); ``marks`` {array: [(time on its clock, label)]}: e.g. the clock steps the estimator found
    (purple dash-dot)."""
    # a Figure on its own Agg canvas, not pyplot (nothing is shown on screen, no global state): pyplot's import
    # and figure manager were ~15 % of the plot's CPU in a fresh process (1.20-1.38 → 1.03-1.09 s, the same pixels)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    arrays = diag["arrays"]
    n = len(arrays)
    fig = Figure(figsize=(FIG_WIDTH_IN, 1.55 * n + 0.9))
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)
    t_max = max(a["duration_s"] for a in arrays.values())
    for ax, (name, a) in zip(axes[:, 0], arrays.items()):
        if "_env" in a:
            t, y, med = a["_env"]   # envelope_summary
            ydb = 20 * np.log10(np.maximum(y, 1e-12) / max(med, 1e-12))
            ax.plot(t, ydb, color="0.45", lw=0.6)
            top = max(float(ydb.max()), 20.0)
        else:
            top = 40.0
        det = a["detections"]
        matched = [d for d in det if d["event"] is not None]
        spurious = [d for d in det if d["event"] is None]
        # one collection per kind, not an artist per line (each axvline is a Line2D with its own transform)
        across = ax.get_xaxis_transform()  # x in data, y from the axes' bottom (0) to top (1)
        ax.vlines([d["time"] for d in matched], 0, 1, transform=across, color="tab:green", lw=1.2, alpha=0.8)
        for t_d, label in _legible([d["time"] for d in matched], [str(d["event"]) for d in matched], t_max):
            ax.text(t_d, top * 1.02, label, color="tab:green", ha="center", va="bottom", fontsize=7)
        if spurious:
            ax.plot([d["time"] for d in spurious], [20 * np.log10(max(d["score"], 1.0)) for d in spurious], "x",
                    color="tab:red", ms=8, mew=2)
        pred = a.get("_predicted")
        if pred is not None and a["missed_events"]:
            te = [pred[diag["event_ids"].index(e)] for e in a["missed_events"]]
            ax.vlines(te, 0, 1, transform=across, color="0.3", linestyles="--", lw=1)
            for t_e, label in _legible(te, [f"{e}?" for e in a["missed_events"]], t_max):
                ax.text(t_e, top * 1.02, label, color="0.3", ha="center", va="bottom", fontsize=7)
        _mark_doubted(ax, a, top)
        for t_m, label in (marks or {}).get(name, ()):
            ax.axvline(t_m, color="tab:purple", ls="-.", lw=1.5)
            ax.text(t_m, top * 0.5, f" {label}", color="tab:purple", ha="left", va="center", fontsize=8)
        n_m = sum(d["event"] is not None for d in det)
        warn = "  ⚠ " + "; ".join(a["warnings"]) if a["warnings"] else ""
        ax.set_title(f"{name}: {n_m} matched, {len(a['missed_events'])} missed "
                     f"({', '.join(map(str, a['missed_events'])) or 'none'}), {len(a['spurious'])} spurious"
                     f"{warn}", fontsize=9, loc="left", y=1.0)   # y given: no search for decorations above the axes
                     # (matplotlib measures every tick label of the axes for it: half of the drawing)
        ax.set_ylim(-5, top * 1.2)
        ax.set_ylabel("dB", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.set_xlim(0, t_max)
    axes[-1, 0].set_xlabel("time on each array's own clock (s)")
    fig.suptitle("Chirp detections: matched-filter envelope; green = matched (event id), red × = spurious, "
                 "dashed = missed event (predicted time)\n▼ distrusted arrival: red = NLOS (reflection only, taken "
                 "out by the estimator), orange = another doubt", fontsize=10)
    _fixed_margins(fig, n)  # tight_layout measured every label: ~0.1 s of a ~0.5 s plot
    fig.savefig(path, dpi=100)
