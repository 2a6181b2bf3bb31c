"""Association of one array's detections with the robot's events.

An array's clock maps emitter time to local time as ``L(t) = (1 + δ)(t − t_0) + τ`` (architecture.md), so
the arrivals follow ``det ≈ offset + scale · (t_emit − t_emit[0])`` up to the propagation delays, which
vary between events by at most the room's size over c. The offset is arbitrary (seconds) and the scale is
within ``1 ± max_drift``. We search that line exhaustively (every detection/event pair as an anchor, on a
grid of scales fine enough for the tolerance), keep the hypothesis that explains most events, refit it on
its matches, and assign one-to-one. Detections left over are spurious; events left over are missed.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def default_tolerance(t_emit, max_range=0.1):
    """Matching tolerance (s): ``max_range`` (≈ 34 m of path-length spread), or less if events are close."""
    t_emit = np.asarray(t_emit, float)
    if len(t_emit) < 2:
        return max_range
    return float(min(max_range, 0.25 * np.min(np.diff(t_emit))))


def _count_matches(det_sorted, pred, tol):
    """Events whose prediction has a detection within ``tol``. pred : (H, K). Returns (H,) counts and
    (H,) sum of squared residuals of those matches."""
    pos = np.searchsorted(det_sorted, pred)
    lo = det_sorted[np.clip(pos - 1, 0, len(det_sorted) - 1)]
    hi = det_sorted[np.clip(pos, 0, len(det_sorted) - 1)]
    res = np.minimum(np.abs(pred - lo), np.abs(pred - hi))
    ok = res <= tol
    return ok.sum(axis=1), np.where(ok, res * res, 0.0).sum(axis=1)


def associate(det_t, det_score, t_emit, tol=None, max_drift=1e-3):
    """Match detections to events.

    Parameters
    ----------
    det_t : (D,) detection times on the array's clock (s).
    det_score : (D,) detection strength (higher = more chirp-like); breaks ties between candidates.
    t_emit : (K,) emission times (s, increasing).
    tol : max |detection − predicted arrival| (s); default :func:`default_tolerance`.
    max_drift : bound on |δ|.

    Returns
    -------
    dict with ``event_of`` ((D,) int, event index or -1 for spurious), ``det_of`` ((K,) int, detection
    index or -1 for missed), ``offset`` and ``scale`` of the fitted line, ``residual_rms`` (s),
    ``n_matched``, ``ambiguous`` (another hypothesis with different matches explains as many events).
    """
    det_t = np.asarray(det_t, float)
    det_score = np.asarray(det_score, float)
    e = np.asarray(t_emit, float) - float(t_emit[0])
    n_det, n_ev = len(det_t), len(e)
    tol = default_tolerance(t_emit) if tol is None else float(tol)
    out = {"event_of": np.full(n_det, -1), "det_of": np.full(n_ev, -1), "offset": np.nan, "scale": np.nan,
           "residual_rms": np.nan, "n_matched": 0, "ambiguous": False, "tolerance": tol}
    if n_det == 0:
        return out
    order = np.argsort(det_t)
    ds = det_t[order]
    span = e[-1] if n_ev > 1 else 0.0
    n_scale = int(np.ceil(2 * max_drift * span / (0.5 * tol))) + 1 if span > 0 else 1
    scales = 1.0 + np.linspace(-max_drift, max_drift, n_scale) if n_scale > 1 else np.ones(1)

    best = None  # (count, -sse, scale, offset)
    hyps = []
    for s in scales:
        offs = (det_t[:, None] - s * e[None, :]).ravel()  # every detection as every event
        cnt, sse = _count_matches(ds, offs[:, None] + s * e[None, :], tol)
        k = np.lexsort((sse, -cnt))[0]
        hyps.append((cnt, sse, s, offs))
        if best is None or (cnt[k], -sse[k]) > (best[0], -best[1]):
            best = (int(cnt[k]), float(sse[k]), s, float(offs[k]))
    _, _, scale, offset = best

    # Refit the line on the current matches (propagation delays average out), then assign one-to-one.
    for _ in range(3):
        match = _assign(det_t, det_score, offset + scale * e, tol)
        j = np.flatnonzero(match >= 0)
        if len(j) >= 2:
            scale, offset = np.polyfit(e[j], det_t[match[j]], 1)
            scale = float(np.clip(scale, 1 - max_drift, 1 + max_drift))
            offset = float(np.mean(det_t[match[j]] - scale * e[j]))
        elif len(j) == 1:
            offset = float(det_t[match[j[0]]] - scale * e[j[0]])
    match = _assign(det_t, det_score, offset + scale * e, tol)
    j = np.flatnonzero(match >= 0)
    out["det_of"] = match
    out["event_of"][match[j]] = j
    res = det_t[match[j]] - (offset + scale * e[j])
    out.update(offset=offset, scale=scale, n_matched=len(j),
               residual_rms=float(np.sqrt(np.mean(res**2))) if len(j) else np.nan)

    # Ambiguity: a hypothesis whose line is far from ours (more than tol at some event) that explains
    # as many events. With irregular emission spacing this does not happen; with a perfectly periodic
    # schedule and a missed first/last event it can, and the user should know.
    if len(j):
        pred = offset + scale * e
        for cnt, sse, s, offs in hyps:
            good = cnt >= len(j)
            if not good.any():
                continue
            other = offs[good][:, None] + s * e[None, :]
            if np.any(np.max(np.abs(other - pred), axis=1) > 2 * tol):
                out["ambiguous"] = True
                break
    return out


def _assign(det_t, det_score, pred, tol):
    """One-to-one matching of detections to predicted arrivals within ``tol``; prefers close and strong.

    Returns (K,) detection index per event or -1.
    """
    n_ev = len(pred)
    res = np.abs(det_t[:, None] - pred[None, :])
    ok = res <= tol
    match = np.full(n_ev, -1)
    if not ok.any():
        return match
    rows = np.flatnonzero(ok.any(axis=1))
    cols = np.flatnonzero(ok.any(axis=0))
    sub_ok = ok[np.ix_(rows, cols)]
    # cost: squared normalised residual minus log strength; a spurious click near a real chirp loses.
    score = np.log(np.maximum(det_score[rows], 1e-12))[:, None]
    cost = (res[np.ix_(rows, cols)] / tol) ** 2 - score
    big = 1e6 + np.abs(cost[sub_ok]).max()
    cost = np.where(sub_ok, cost - big, 0.0)  # any valid match beats none
    r, c = linear_sum_assignment(cost)
    keep = sub_ok[r, c]
    match[cols[c[keep]]] = rows[r[keep]]
    return match
