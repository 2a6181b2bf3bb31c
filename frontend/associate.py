"""Association of one array's detections with the robot's events, in O(K log K).

An array's clock maps emitter time to local time as ``L(t) = (1 + δ)(t − t_0) + τ`` (architecture.md), so
the arrivals follow ``det ≈ offset + scale · (t_emit − t_emit[0])`` up to the propagation delays, which
vary between events by at most the room's size over c (the matching tolerance). The offset is arbitrary
(seconds) and the scale is within ``1 ± max_drift``. The line is found without trying every
(detection, event, scale) triple:

1. **Local hypotheses.** In a few short windows of consecutive events (start, middle and end of the
   schedule) every detection is tried as every window event, on a scale grid fine enough for the window's
   length (one or two scales: over a few tens of seconds the drift moves nothing by more than a fraction
   of the tolerance). The hypotheses that explain most of the window's events are kept (a few per window).
2. **Growth.** Each kept hypothesis is extended over a doubling span of events around its window; at each
   span the scale is re-searched on a grid of constant size around the previous estimate (the grid step
   halves as the span doubles), so the cost is O(K log D) per hypothesis.
3. **Global offsets.** At the best scale, the number of (detection, event) pairs within the tolerance of
   every offset is one cross-correlation of the two time histograms (FFT, linear in the duration); its
   highest peaks are scored exactly. This catches alignments no window saw (a periodic schedule
   shifted by whole periods) and is what decides ambiguity.

The line that explains most events (ties: smallest squared residuals) is refitted on its matches and
detections are assigned one-to-one (a sorted merge; a small Hungarian problem only where the tolerance
windows of neighbouring events overlap). Detections left over are spurious; events left over are missed.
"""
from __future__ import annotations

import numpy as np
import scipy.fft as sfft

WINDOW_EVENTS = 8      # events per local window: enough to make an irregular pattern unique
PIVOT_EVENTS = 3       # window events tried as each detection (one of them is rarely missed)
N_WINDOWS = 3          # windows at the start, middle and end (an array may miss a stretch of the session)
KEEP_PER_WINDOW = 8    # distinct local hypotheses grown per window
RIGID_FRACTION = 0.125  # scale-grid step: the line moves by at most this × tol over the span searched
N_OFFSET_PEAKS = 8     # peaks of the global offset correlation scored exactly
HIST_BINS_PER_TOL = 2  # resolution of the offset histograms (bins per tolerance)
MAX_DEDUP_SCAN = 20000  # hypotheses scanned (best first) when picking distinct ones from a window


def default_tolerance(t_emit, max_range=0.1):
    """Matching tolerance (s): ``max_range`` (≈ 34 m of path-length spread), or less if events are close."""
    t_emit = np.asarray(t_emit, float)
    if len(t_emit) < 2:
        return max_range
    return float(min(max_range, 0.25 * np.min(np.diff(t_emit))))


def _nearest(ds, pred):
    """Signed residual (detection − prediction) to the nearest sorted detection. pred : any shape."""
    pos = np.searchsorted(ds, pred)
    lo = ds[np.clip(pos - 1, 0, len(ds) - 1)]
    hi = ds[np.clip(pos, 0, len(ds) - 1)]
    return np.where(np.abs(pred - lo) <= np.abs(hi - pred), lo - pred, hi - pred)


def _count_matches(ds, pred, tol):
    """Events whose prediction has a detection within ``tol``. pred : (H, K). Returns (H,) counts and
    (H,) sum of squared residuals of those matches."""
    res = np.abs(_nearest(ds, pred))
    ok = res <= tol
    return ok.sum(axis=1), np.where(ok, res * res, 0.0).sum(axis=1)


def _scale_grid(lo, hi, step, max_drift):
    """Scales from ``lo`` to ``hi`` (clipped to 1 ± max_drift) at most ``step`` apart. Returns (G,)."""
    lo, hi = max(lo, 1.0 - max_drift), min(hi, 1.0 + max_drift)
    if hi <= lo or step <= 0 or not np.isfinite(step):
        return np.array([0.5 * (lo + hi)])
    return np.linspace(lo, hi, int(np.ceil((hi - lo) / step)) + 1)


def _step_for(span, tol):
    """Scale-grid step for events up to ``span`` s from the pivot: the line moves ≤ RIGID_FRACTION × tol."""
    return RIGID_FRACTION * tol / span if span > 0 else np.inf


def _windows(n_ev):
    """Index ranges (start, stop) of the local windows: the first, middle and last WINDOW_EVENTS events."""
    w = min(WINDOW_EVENTS, n_ev)
    starts = np.unique(np.round(np.linspace(0, n_ev - w, min(N_WINDOWS, n_ev - w + 1))).astype(int))
    return [(int(s), int(s) + w) for s in starts]


def _local_hypotheses(ds, e, window, tol, max_drift):
    """Best distinct lines through one window of events.

    Every detection as each of the window's first PIVOT_EVENTS events, on a scale grid for the window's
    length (the line moves by at most tol / 4 over half the window between grid scales). Returns a list of
    (pivot_e, pivot_t, scale, step) — the line ``t = pivot_t + scale (e − pivot_e)`` — best first.
    """
    ew = e[window[0]:window[1]]
    centre = 0.5 * (ew[0] + ew[-1])
    step = 0.25 * tol / (0.5 * (ew[-1] - ew[0])) if ew[-1] > ew[0] else np.inf
    scales = _scale_grid(1.0 - max_drift, 1.0 + max_drift, step, max_drift)
    # hypothesis (g, i, j): detection i is window event j at scale g; t_c: the line at the window's centre
    piv = ew[:PIVOT_EVENTS]
    t_c = (ds[None, :, None] + scales[:, None, None] * (centre - piv[None, None, :])).ravel()  # (G·D·P,)
    g_of = np.repeat(np.arange(len(scales)), len(ds) * len(piv))
    pred = t_c[:, None] + scales[g_of][:, None] * (ew - centre)[None, :]
    cnt, sse = _count_matches(ds, pred, tol)
    order = np.lexsort((sse, -cnt))[:MAX_DEDUP_SCAN]
    picked = []
    for h in order:
        if cnt[h] < cnt[order[0]] - len(ew) // 2 or len(picked) >= KEEP_PER_WINDOW:
            break
        if all(abs(t_c[h] - p[1]) > 2 * tol for p in picked):
            picked.append((centre, float(t_c[h]), float(scales[g_of[h]]), min(step, 2 * max_drift)))
    return picked


def _grow(ds, e, hyp, tol, max_drift):
    """Extend a local line over all events: doubling spans around its pivot, the scale re-searched at each.

    hyp : (pivot_e, pivot_t, scale, step). Returns (offset, scale) of ``t = offset + scale e``.
    """
    ec, tc, s, step = hyp
    far = max(ec - e[0], e[-1] - ec)
    span = max(RIGID_FRACTION * tol / max_drift if max_drift > 0 else far, 1e-9)
    while span < far:
        span = min(2 * span, far)
        i0, i1 = np.searchsorted(e, ec - span, side="left"), np.searchsorted(e, ec + span, side="right")
        de = e[i0:i1] - ec
        new_step = _step_for(span, tol)
        scales = _scale_grid(s - 2 * step, s + 2 * step, new_step, max_drift)
        cnt, sse = _count_matches(ds, tc + scales[:, None] * de[None, :], tol)
        k = np.lexsort((sse, -cnt))[0]
        s, step = float(scales[k]), new_step
        res = _nearest(ds, tc + s * de)
        ok = np.abs(res) <= tol
        if ok.any():  # recentre the pivot on the matches (propagation delays average out)
            tc += float(np.median(res[ok]))
    return tc - s * ec, s


def _offset_peaks(ds, e_scaled, tol):
    """Offsets ``o`` (t = o + e_scaled) where most (detection, event) pairs agree, from the cross-correlation
    of the two time histograms (FFT). Returns (P,) offsets, best first."""
    b = tol / HIST_BINS_PER_TOL
    nx = int(np.ceil((ds[-1] - ds[0]) / b)) + 1
    ny = int(np.ceil((e_scaled[-1] - e_scaled[0]) / b)) + 1
    hx = np.bincount(np.floor((ds - ds[0]) / b).astype(int), minlength=nx).astype(float)
    hy = np.bincount(np.floor((e_scaled[-1] - e_scaled) / b).astype(int), minlength=ny).astype(float)
    n = sfft.next_fast_len(nx + ny, real=True)
    corr = sfft.irfft(sfft.rfft(hx, n) * sfft.rfft(hy, n), n)[: nx + ny - 1]
    corr = np.convolve(corr, np.ones(2 * HIST_BINS_PER_TOL + 1), "same")  # pairs within ≈ ± tol
    # bin k = k_x + k_y, k_x = ⌊(t − ds[0]) / b⌋, k_y = ⌊(e[-1] − e) / b⌋ ⇒ t − e ≈ ds[0] − e[-1] + (k + 1) b
    n_top = min(len(corr), 50 * N_OFFSET_PEAKS)
    top = np.argpartition(corr, len(corr) - n_top)[len(corr) - n_top:]
    top = top[np.argsort(corr[top])[::-1]]
    picked = []
    for k in top:
        if len(picked) >= N_OFFSET_PEAKS or corr[k] <= 0:
            break
        if all(abs(k - p) > 2 * HIST_BINS_PER_TOL for p in picked):
            picked.append(k)
    return ds[0] - e_scaled[-1] + (np.asarray(picked, float) + 1.0) * b  # + the floors' mean loss


def _score_lines(ds, e, lines, tol):
    """Exact counts and squared residuals of lines (offset, scale) over all events. Returns (L,), (L,)."""
    off = np.array([l[0] for l in lines])
    sc = np.array([l[1] for l in lines])
    return _count_matches(ds, off[:, None] + sc[:, None] * e[None, :], tol)


def candidate_lines(ds, e, tol, max_drift):
    """All lines (offset, scale) worth scoring: grown local hypotheses and global offset peaks."""
    lines = []
    for w in _windows(len(e)):
        lines += [_grow(ds, e, h, tol, max_drift) for h in _local_hypotheses(ds, e, w, tol, max_drift)]
    if not lines:
        lines = [(ds[0], 1.0)]
    cnt, sse = _score_lines(ds, e, lines, tol)
    s_best = lines[np.lexsort((sse, -cnt))[0]][1]
    lines += [(float(o), s_best) for o in _offset_peaks(ds, s_best * e, tol)]
    return [_recentre(ds, e, line, tol) for line in lines]


def _recentre(ds, e, line, tol):
    """Shift a line (offset, scale) by the median residual of its matches."""
    offset, scale = line
    res = _nearest(ds, offset + scale * e)
    ok = np.abs(res) <= tol
    return (offset + float(np.median(res[ok])), scale) if ok.any() else (offset, scale)


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
    ``n_matched``, ``ambiguous`` (another line, more than 2 tol away from ours at some event, explains as
    many events), ``tolerance``.
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
    order = np.argsort(det_t, kind="stable")
    ds = det_t[order]
    if n_ev == 1:  # nothing to align: the strongest detection
        lines = [(float(det_t[np.argmax(det_score)]), 1.0)]
    else:
        lines = candidate_lines(ds, e, tol, max_drift)
    cnt, sse = _score_lines(ds, e, lines, tol)
    offset, scale = lines[np.lexsort((sse, -cnt))[0]]

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

    # Ambiguity: a line far from ours (more than 2 tol at some event; lines differ most at the ends) that
    # explains as many events. With irregular emission spacing this does not happen; with a perfectly
    # periodic schedule and a missed first/last event it can, and the user should know.
    if len(j) and n_ev > 1:
        ends = np.array([e[0], e[-1]])
        far = [np.max(np.abs(o + s * ends - (offset + scale * ends))) > 2 * tol for o, s in lines]
        out["ambiguous"] = bool(np.any(np.asarray(far) & (cnt >= len(j))))
    return out


def _assign(det_t, det_score, pred, tol):
    """One-to-one matching of detections to predicted arrivals within ``tol``; prefers close and strong.

    Candidate pairs come from a sorted merge; where a detection is within ``tol`` of several events (or an
    event has several detections) the connected group is solved as a small assignment problem.
    pred : (K,) increasing. Returns (K,) detection index per event or -1.
    """
    n_ev = len(pred)
    match = np.full(n_ev, -1)
    order = np.argsort(det_t, kind="stable")
    ds = det_t[order]
    lo = np.searchsorted(ds, pred - tol, side="left")
    hi = np.searchsorted(ds, pred + tol, side="right")
    n_pair = hi - lo
    if not n_pair.any():
        return match
    ev = np.repeat(np.arange(n_ev), n_pair)
    pos = np.arange(n_pair.sum()) - np.repeat(np.cumsum(n_pair) - n_pair, n_pair) + np.repeat(lo, n_pair)
    det = order[pos]
    # cost: squared normalised residual minus log strength; a spurious click near a real chirp loses.
    cost = ((det_t[det] - pred[ev]) / tol) ** 2 - np.log(np.maximum(det_score[det], 1e-12))
    uses = np.bincount(det, minlength=len(det_t))
    simple = uses[det] == 1
    # events whose candidate detections are used by no other event: take the cheapest candidate
    ev_simple = np.ones(n_ev, bool)
    np.logical_and.at(ev_simple, ev, simple)
    sel = ev_simple[ev]
    if sel.any():
        k = np.lexsort((cost[sel], ev[sel]))
        first = np.r_[True, np.diff(ev[sel][k]) != 0]
        match[ev[sel][k][first]] = det[sel][k][first]
    if (~sel).any():
        _assign_groups(match, ev[~sel], det[~sel], cost[~sel], len(det_t))
    return match


def _assign_groups(match, ev, det, cost, n_det):
    """Hungarian assignment within each connected group of (event, detection) candidate pairs."""
    # imported here: scipy.optimize and scipy.sparse cost ~0.14 s of CPU to import, and most sessions have no
    # detection that two events contend for (a `calib features` process then never loads them)
    from scipy.optimize import linear_sum_assignment
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_ev = len(match)
    g = coo_matrix((np.ones(len(ev)), (ev, n_ev + det)), shape=(n_ev + n_det,) * 2)
    _, label = connected_components(g, directed=False)
    grp = label[ev]
    for lab in np.unique(grp):
        m = grp == lab
        evs, ev_i = np.unique(ev[m], return_inverse=True)
        dets, det_i = np.unique(det[m], return_inverse=True)
        c = np.zeros((len(dets), len(evs)))
        ok = np.zeros_like(c, bool)
        c[det_i, ev_i], ok[det_i, ev_i] = cost[m], True
        big = 1e6 + np.abs(c[ok]).max()
        r, col = linear_sum_assignment(np.where(ok, c - big, 0.0))  # any valid match beats none
        keep = ok[r, col]
        match[evs[col[keep]]] = dets[r[keep]]
