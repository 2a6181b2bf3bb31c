"""Deterministic initialisation (no ground truth, no random restarts).

1. Sources: the reference array's DOAs are rays from the origin; the odometry fixes the sources up to
   one start point ``s_0``, found by linear least squares (rays vs. ``s_0 + odom_j``). A small NLS on
   the reference array's own measurements (DOA, TDOA-S, odometry) then refines sources and its drift.
2. Arrays, one at a time with the sources fixed: a coarse 3-D grid over positions where, at each grid
   point, offset and drift are solved in closed form (robust IRLS on TDOA-S + TDOA-M) and the rotation
   by Kabsch alignment of DOAs (SVD), the DOAs' misfit judged robustly (Cauchy, :func:`robust_kabsch`); the
   best few local minima are polished by LM and the best is kept.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from calib.errors import InputError
from calib.geometry import fold, mirror

from .ambiguity import separation
from .problem import empty_state, make_layout
from .solver import levenberg_marquardt, linearise


# The grid search of each array's pose uses at most this many events (evenly spaced): enough to rank grid
# points far beyond the noise, and it keeps the initialisation linear in the number of events.
GRID_MAX_EVENTS = 100


class ObservabilityError(InputError):
    """The data cannot determine the calibration (the message says what is missing): bad input, not a bug."""


def subproblem(p, arrays, *, doa_arrays=None):
    """The problem restricted to measurements of ``arrays`` (TDOA-M rows also need the reference).

    ``doa_arrays`` (default ``arrays``) selects whose DOAs are kept.
    """
    arrays = np.asarray(arrays)
    doa_arrays = arrays if doa_arrays is None else np.asarray(doa_arrays)
    return p.replace(tdoa_m=p.tdoa_m.select(np.isin(p.tdoa_m.arr, arrays)),
                     tdoa_s=p.tdoa_s.select(np.isin(p.tdoa_s.arr, arrays)),
                     doa=p.doa.select(np.isin(p.doa.arr, doa_arrays)))


def kabsch(u, v, w=None):
    """Rotation(s) R minimising Σ w |R u − v|². u, v: (..., n, 3) → R (..., 3, 3), cost (...)."""
    w = np.ones(np.broadcast_shapes(u.shape, v.shape)[:-1]) if w is None else w
    M = np.matmul(np.swapaxes(v * w[..., None], -1, -2), u)   # Σ w v uᵀ (batched BLAS beats einsum here)
    A, S, Bt = np.linalg.svd(M)
    sgn = np.sign(np.linalg.det(A @ Bt))
    sgn = np.where(sgn == 0, 1.0, sgn)
    D = np.ones(S.shape)
    D[..., 2] = sgn
    R = A @ (D[..., :, None] * Bt)
    cost = 2.0 * w.sum(-1) - 2.0 * (S * D).sum(-1)
    return R, np.maximum(cost, 0.0)


def init_sources(p):
    """Source hypotheses s_j = s_0 + odom_j with s_0 from the reference array's DOA rays (linear LS).

    Returns a list of (K, 3) arrays: one, or for a mirror-ambiguous (planar) reference array one per
    self-consistent choice of the events behind its plane (the caller keeps the best after refinement).
    """
    ref = p.ref
    m = p.doa.arr == ref
    if m.sum() < 2:
        raise ObservabilityError(
            f"the reference array {p.names[ref]} has DOAs for {int(m.sum())} event(s); at least 2 are needed "
            "to place the sources in its frame")
    u, j = p.doa.u[m], p.doa.ev[m]
    o = p.odom - p.odom[0]

    def solve(u):
        P = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
        A = P.sum(0)
        if np.linalg.cond(A) > 1e8:
            raise ObservabilityError(f"the reference array {p.names[ref]}'s DOAs are all parallel: "
                                     "the source start point is undetermined")
        return np.linalg.solve(A, -np.einsum("kab,kb->a", P, o[j]))

    n = p.fold[ref]
    if not np.any(n):
        return [solve(u) + o]
    return [s0 + o for s0 in _folded_start_points(u, o[j], n)]


def _folded_start_points(u, oj, n, n_keep=3, zoom_levels=6):
    """Start points s_0 for a mirror-ambiguous reference array (R = I, plane normal n known).

    Grid search of the folded-DOA misfit Σ_j |fold(dir(s_0 + o_j)) − u_j|² over s_0, then zoom into the
    best local minima; returns up to ``n_keep`` of them, best first. (The linear triangulation cannot be
    used: which events lie behind the plane is unknown.)
    """
    def misfit(s0):  # s0 (G, 3)
        v = s0[:, None, :] + oj[None]
        v = v / np.maximum(np.linalg.norm(v, axis=2, keepdims=True), 1e-9)
        v = fold(v, n)
        return ((v - u[None]) ** 2).sum((1, 2))

    span = max(5.0, 2.0 * float(np.max(np.ptp(oj, axis=0))))
    grid, step = grid_points(np.array([[-span, -span, -span], [span, span, span]]), n_per_axis=28, margin=0.0)
    shape, pts = grid.shape[:3], grid.reshape(-1, 3)
    c = misfit(pts)
    C = c.reshape(shape)
    cand = np.flatnonzero((C == minimum_filter(C, size=3, mode="nearest")).ravel())
    cand = cand[np.argsort(c[cand])][:n_keep]
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    out = []
    for g in cand:
        centre, h = pts[g], step
        for _ in range(zoom_levels):
            h *= 0.5
            sub = centre + h * offsets
            centre = sub[int(np.argmin(misfit(sub)))]
        out.append(centre)
    return out


def refine_reference(p, st):
    """NLS on the reference array's own measurements: sources and (with TDOA-S) its drift."""
    ref = p.ref
    q = subproblem(p, [ref])  # TDOA-M rows never name the reference, so this keeps none of them
    lay = make_layout(q, arrays=[ref], emission=False)
    st, info = levenberg_marquardt(q, st, lay, ["tdoa_s", "doa", "odometry"], loss="cauchy", k=3.0, max_iter=50,
                                   rtol=1e-6)
    return st, info, q, lay


def source_spread(q, st, lay):
    """RMS 1-σ source position uncertainty (m) of the reference-only solve (floored at 2 cm)."""
    from .uncertainty import cov_diagonal, covariance

    J = linearise(q, st, lay, ["tdoa_s", "doa", "odometry"]).J
    cols = lay.s.ravel()
    try:
        var = cov_diagonal(covariance(J, lay.n, lay))[cols]
        return max(float(np.sqrt(np.mean(var) * 3)), 0.02)
    except (np.linalg.LinAlgError, RuntimeError):
        return 0.3


def grid_points(s, n_per_axis=12, margin=None):
    """A regular grid around the sources: (nx, ny, nz, 3) points."""
    lo, hi = s.min(0), s.max(0)
    ext = float(np.max(hi - lo))
    margin = max(1.0, 0.35 * ext) if margin is None else margin
    lo, hi = lo - margin, hi + margin
    step = float(np.max(hi - lo)) / n_per_axis
    axes = [np.arange(lo[k], hi[k] + 0.5 * step, step) for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1), step


def profile_cost(p, st, i, pts, kappa, sigma_d, n_irls=6):
    """Concentrated cost of array ``i`` at candidate positions ``pts`` (G, 3), sources fixed.

    Drift and offset are solved in closed form per point (robust Cauchy IRLS, scale ``kappa`` s) from
    TDOA-S and TDOA-M; the rotation by Kabsch on the DOAs (per-axis scale ``sigma_d`` rad).
    Returns cost (G,), drift (G,), offset (G,). (The shared coarse grid: :func:`coarse_cost`.)
    """
    G = len(pts)
    X, Y, ns, use_off = _clock_columns(p, st, i, pts)
    drift, off, r2 = _clock_irls(X, Y, ns, kappa, use_off, n_irls)
    cost = np.log1p(r2).sum(1)
    md = p.doa.arr == i
    if md.sum() >= 2:
        u, v = _doa_columns(p, st, i, pts)
        if np.any(p.fold[i]):
            normals = _NORMALS_COARSE if G > 500 else _NORMALS
            kc = np.minimum(*[doa_cost(uu, v, sigma_d) for uu in unfold_candidates(u, p.fold[i], v, normals)])
        else:
            kc = doa_cost(u, v, sigma_d)
        cost = cost + kc
    cones = _cone_rows(p, st, i)
    if cones is not None:
        cost = cost + cone_cost(cones[0], _directions(cones[1], pts), sigma_d)[0]
    return cost, drift, off


def coarse_cost(p, st, i, kappa, sigma_d, grid, n_irls=6):
    """:func:`profile_cost` of array ``i`` at every point of the shared coarse grid (:func:`coarse_grid`),
    which only ranks candidates for the zoom, so it is computed for speed, the same values up to rounding:
    in the grid's transposed layout (measurements × points: the IRLS sums run along contiguous rows of
    points). Returns cost (G,).
    """
    G = len(grid["pts"])
    XT, YT, ns, use_off = _clock_columns_t(p, st, i, grid)
    r2 = _clock_irls_masked(XT, YT, np.ones(XT.shape), ns, kappa, np.full(G, bool(use_off)), n_irls)[2]
    cost = np.log1p(r2).sum(0)
    cones = _cone_rows(p, st, i, grid["col"])
    if cones is not None:
        cost = cost + cone_cost(cones[0], grid["u"][:, grid["col"][cones[2]]], sigma_d)[0]
    md = p.doa.arr == i
    if md.sum() < 2:
        return cost
    u, ev = p.doa.u[md], p.doa.ev[md]
    v = grid["u"][:, grid["col"][ev]]
    if np.any(p.fold[i]):
        normals = _NORMALS_COARSE if G > 500 else _NORMALS
        kc = np.minimum(*[doa_cost(uu, v, sigma_d) for uu in unfold_candidates(u, p.fold[i], v, normals)])
    else:
        kc = doa_cost(u, v, sigma_d)
    return cost + kc


def _clock_rows(p, st, i):
    """Array ``i``'s TDOA rows in the clock model, the parts that do not depend on the candidate points
    (computed once for all zoom levels): the rows' events, values and reference-array terms, and the
    events they name (``need``) with each event's column among them (``col``)."""
    c, beta, ref, s, t = p.c, p.beta, p.ref, st.s, p.t
    ms, mm = p.tdoa_s.arr == i, p.tdoa_m.arr == i
    a, b, zs = p.tdoa_s.a[ms], p.tdoa_s.b[ms], p.tdoa_s.val[ms]
    j, zm = p.tdoa_m.ev[mm], p.tdoa_m.val[mm]
    need = np.unique(np.concatenate([a, b, j]))                    # the events these rows name
    col = np.zeros(len(s), int)
    col[need] = np.arange(len(need))
    dr = np.linalg.norm(s[j] - st.x[ref], axis=1)
    g0 = 1.0 + st.drift[ref]
    return {"a": a, "b": b, "j": j, "zs": zs[None], "zm": zm[None], "dt": (t[b] - t[a])[None], "tj": t[j][None],
            "yref": (g0 * (t[j] + dr / c) + beta * st.drift[ref])[None], "src": s[need][None, :, :],
            "col": col, "use_off": bool(mm.sum() >= 2)}


def _clock_columns(p, st, i, pts, rows=None):
    """The clock model of array ``i`` at points ``pts``: δ·X + off·[columns ns:] = Y, X and Y (G, ns + nm)
    with the TDOA-S columns first. ``rows``: :func:`_clock_rows` (computed if None). Returns X, Y, ns,
    whether the offset is solved (>= 2 TDOA-M rows)."""
    q = _clock_rows(p, st, i) if rows is None else rows
    c, a, b, j, col = p.c, q["a"], q["b"], q["j"], q["col"]
    d = np.linalg.norm(q["src"] - pts[:, None, :], axis=2)  # (G, events named)
    h = q["dt"] + (d[:, col[b]] - d[:, col[a]]) / c
    dj = q["tj"] + d[:, col[j]] / c
    X = np.concatenate([h, dj + p.beta], axis=1)
    Y = np.concatenate([q["zs"] - h, q["zm"] - dj + q["yref"]], axis=1)
    return X, Y, len(a), q["use_off"]


def _clock_columns_t(p, st, i, grid):
    """:func:`_clock_columns` at the points of the coarse grid, transposed: XT, YT (ns + nm, G) from the
    grid's distances ``dT`` (E, G). Returns XT, YT, ns, whether the offset is solved."""
    q = _clock_rows(p, st, i)
    c, a, b, j, col, dT = p.c, q["a"], q["b"], q["j"], grid["col"], grid["dT"]
    h = q["dt"].T + (dT[col[b]] - dT[col[a]]) / c
    dj = q["tj"].T + dT[col[j]] / c
    XT = np.concatenate([h, dj + p.beta], axis=0)
    YT = np.concatenate([q["zs"].T - h, q["zm"].T - dj + q["yref"].T], axis=0)
    return XT, YT, len(a), q["use_off"]


def _doa_rows(p, st, i):
    """Array ``i``'s measured DOAs u (n, 3) and their sources (n, 3), or None with fewer than 2 DOAs."""
    md = p.doa.arr == i
    return (p.doa.u[md], st.s[p.doa.ev[md]]) if md.sum() >= 2 else None


def _doa_columns(p, st, i, pts):
    """Array ``i``'s measured DOAs u (n, 3) and the unit directions v (G, n, 3) from ``pts`` to their sources."""
    md = p.doa.arr == i
    return p.doa.u[md], _directions(st.s[p.doa.ev[md]], pts)


def profile_cost_many(items, st, kappa, sigma_d, n_irls=6, rows=None):
    """:func:`profile_cost` (no shared grid) of several arrays, each at its own points, in one evaluation.

    ``items``: [(problem, array index, points (G_k, 3))]. The zoom evaluates ~125 points per array, where
    numpy's per-call overhead dominates; stacking the arrays' rows (columns padded with zero weight, DOAs
    with zero vectors, which add nothing to the Kabsch matrix) makes one evaluation of all of them (the
    same values up to rounding). Mirror-folded arrays take :func:`profile_cost` one by one. ``rows``:
    each item's (:func:`_clock_rows`, :func:`_doa_rows`), kept by the caller across zoom levels (None:
    computed here). Returns cost, drift, offset, each concatenated over the items in order.
    """
    if len(items) == 1 or any(np.any(p.fold[i]) or _cone_rows(p, st, i) is not None for p, i, _ in items):
        out = [profile_cost(p, st, i, pts, kappa, sigma_d, n_irls) for p, i, pts in items]
        return tuple(np.concatenate(z) for z in zip(*out))
    rows = [(_clock_rows(p, st, i), _doa_rows(p, st, i)) for p, i, _ in items] if rows is None else rows
    clock = [_clock_columns(p, st, i, pts, rows=r[0]) for (p, i, pts), r in zip(items, rows)]
    S = max(q[2] for q in clock)
    M = max(q[0].shape[1] - q[2] for q in clock)
    G = sum(len(q[0]) for q in clock)
    # the clock columns transposed, (S + M, G): the IRLS sums run along contiguous rows of points
    XT, YT, maskT, use_off = np.zeros((S + M, G)), np.zeros((S + M, G)), np.zeros((S + M, G)), np.zeros(G, bool)
    doa = [None if r[1] is None else (r[1][0], _directions(r[1][1], pts)) for (_, _, pts), r in zip(items, rows)]
    D = max([len(q[0]) for q in doa if q is not None], default=0)
    U, V, nd = np.zeros((G, D, 3)), np.zeros((G, D, 3)), np.zeros(G)
    g0 = 0
    for (x, y, ns, uo), dq in zip(clock, doa):
        g1, nm = g0 + len(x), x.shape[1] - ns
        for dst, src in ((XT, x), (YT, y)):
            dst[:ns, g0:g1], dst[S:S + nm, g0:g1] = src[:, :ns].T, src[:, ns:].T
        maskT[:ns, g0:g1], maskT[S:S + nm, g0:g1] = 1.0, 1.0
        use_off[g0:g1] = uo
        if dq is not None:
            U[g0:g1, :len(dq[0])], V[g0:g1, :len(dq[0])], nd[g0:g1] = dq[0], dq[1], len(dq[0])
        g0 = g1
    drift, off, r2 = _clock_irls_masked(XT, YT, maskT, S, kappa, use_off, n_irls)
    cost = (np.log1p(r2) * maskT).sum(0)
    if D:   # nd = 0 rows: exactly 0 added
        cost = cost + doa_cost(U, V, sigma_d)   # (zero rows add nothing to either)
    return cost, drift, off


def _clock_irls_masked(XT, YT, mask, ns, kappa, use_off, n_irls):
    """:func:`_clock_irls` on transposed columns XT, YT (n, G) (rows of points) with a weight
    mask (n, G) (0 = padding) and ``use_off`` per point (G,). Returns drift (G,), offset (G,) and the
    last squared normalised residuals (n, G)."""
    G = XT.shape[1]
    XT, YT = XT / kappa, YT / kappa   # residuals in units of kappa directly (the drift does not change)
    w = mask.copy()
    drift, off = np.zeros(G), np.zeros(G)
    wX, r = np.empty_like(XT), np.empty_like(XT)
    for it in range(n_irls):
        np.multiply(w, XT, out=wX)
        a11, b1 = np.einsum("kg,kg->g", wX, XT), np.einsum("kg,kg->g", wX, YT)
        a12, a22, b2 = wX[ns:].sum(0), w[ns:].sum(0), np.einsum("kg,kg->g", w[ns:], YT[ns:])
        det = a11 * a22 - a12 * a12
        ok = use_off & (np.abs(det) > 1e-300)
        only = ~use_off & (a11 > 0)
        drift_only = np.where(only, b1 / np.where(only, a11, 1), 0.0)   # points without an offset
        drift = np.where(ok, (b1 * a22 - a12 * b2) / np.where(ok, det, 1), drift_only)
        off = np.where(ok, (a11 * b2 - a12 * b1) / np.where(ok, det, 1), 0.0)
        _squared_residuals(XT, YT, drift, off, ns, r)   # r2 = (r / kappa)²
        if it + 1 < n_irls:          # (the last weights would not be used)
            np.add(r, 1.0, out=w)
            np.divide(mask, w, out=w)
    return drift, off * kappa, r


def _squared_residuals(XT, YT, drift, off, ns, out):
    """(YT − drift·XT − off on rows ns:)² into ``out`` (n, G), in place: the clock IRLS's squared residuals."""
    np.multiply(drift, XT, out=out)
    np.subtract(YT, out, out=out)
    out[ns:] -= off
    np.square(out, out=out)
    return out


def _clock_irls(X, Y, ns, kappa, use_off, n_irls):
    """Drift (and offset) per row of the model δ·X + off·[columns ns:] = Y by Cauchy IRLS (scale kappa).

    X, Y (G, n): the first ``ns`` columns are TDOA-S (no offset), the rest TDOA-M. Returns drift (G,),
    offset (G,) and the last squared normalised residuals (G, n): :func:`_clock_irls_masked` with every
    column weighted and the same ``use_off`` for every row.
    """
    drift, off, r2 = _clock_irls_masked(np.ascontiguousarray(X.T), np.ascontiguousarray(Y.T), np.ones(X.shape[::-1]),
                                        ns, kappa, np.full(len(X), bool(use_off)), n_irls)
    return drift, off, r2.T


def coarse_grid(s, events=None):
    """The coarse search grid around sources ``s`` (K, 3) and its geometry, shared by every array.

    ``events`` (E,) restricts the geometry to those events (default all), so its memory stays bounded
    (G × E) however many events there are. Returns dict: ``pts`` (G, 3), ``shape`` (3,), ``step`` (m),
    ``dT`` (E, G) distances (transposed: :func:`coarse_cost`'s layout) and ``u`` (G, E, 3) unit directions
    from each point to each of those sources, ``col`` (K,) the column of each event (-1 if not included), ``dmin`` (G,) distance to the nearest
    source of all K.
    """
    events = np.arange(len(s)) if events is None else np.asarray(events, int)
    grid, step = grid_points(s)
    pts = grid.reshape(-1, 3)
    w = s[events][None] - pts[:, None, :]
    d = np.linalg.norm(w, axis=2)
    col = np.full(len(s), -1)
    col[events] = np.arange(len(events))
    u = w / d[..., None]
    return {"pts": pts, "shape": grid.shape[:3], "step": step, "dT": np.ascontiguousarray(d.T), "u": u, "col": col,
            # (with every event in the geometry its distances give it; a KD-tree only for a subsample)
            "dmin": d.min(axis=1) if len(events) == len(s) else cKDTree(s).query(pts)[0]}


def _directions(src, pts):
    """Unit vectors (G, n, 3) from points (G, 3) to sources (n, 3)."""
    v = src[None] - pts[:, None, :]
    return v / np.linalg.norm(v, axis=2, keepdims=True)


MIN_CONE_ROWS = 3  # cone rows that determine a linear board's or a pair's axis (three unknowns)
DOA_ROBUST = 3.0   # the DOA term's Cauchy scale, in σ_d (the clock term's: 3 σ_tdoa)
DOA_IRLS = 2       # reweighted Kabsch fits after the first, for an array's rotation at its chosen start


def _cone_rows(p, st, i, col=None):
    """Array ``i``'s cone rows (a linear board or a pair: cos θ to its axis) as (cos (n,), their sources (n, 3),
    their events (n,)), or None with fewer than MIN_CONE_ROWS of them (the axis is three unknowns). ``col``:
    the coarse grid's event columns (rows of events outside it are left out)."""
    mc = p.cone.arr == i
    if col is not None:
        mc &= col[p.cone.ev] >= 0
    if mc.sum() < MIN_CONE_ROWS:
        return None
    return p.cone.cos[mc], st.s[p.cone.ev[mc]], p.cone.ev[mc]


def cone_cost(c, v, sigma_d):
    """The cone term of the concentrated cost (G,) and the best axis (G, 3) (world frame) of cone rows cos θ ``c``
    (n,) against directions v (G, n, 3): the axis by linear least squares of v â = c, normalised (a
    Kabsch for cones), its misfit judged as :func:`robust_kabsch`'s (Cauchy, scale DOA_ROBUST σ_d; the cosine's
    error is sin θ δθ ≤ δθ). Without it a linear board or a pair is placed by its arrivals alone, where a few
    late ones can make a wrong basin the lowest (a pair's start 55 cm off in height, its cones 100 σ off there)."""
    A = np.einsum("gna,gnb->gab", v, v) + 1e-9 * np.eye(3)
    a = np.linalg.solve(A, np.einsum("gna,n->ga", v, c)[..., None])[..., 0]
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    e = np.einsum("gna,ga->gn", v, a) - c
    c2 = (DOA_ROBUST * sigma_d) ** 2
    return c2 / (2.0 * sigma_d ** 2) * np.log1p(e * e / c2).sum(-1), a


def robust_kabsch(u, v, sigma_d, iters=DOA_IRLS):
    """Rotations R (G, 3, 3) and the DOA term of the concentrated cost (G,) of DOAs u ((n, 3) or (G, n, 3)) against
    directions v (G, n, 3): Σ (c²/2σ²) log(1 + |R u − v|²/c²), c = DOA_ROBUST σ_d, R by :func:`kabsch` reweighted
    ``iters`` times (IRLS). Within a few σ it is the quadratic Σ |R u − v|²/2σ²; a DOA tens of degrees off (a
    reflection's, or several paths': office seed 10, A4, one of 14 DOAs 70° off with the type's σ 0.8°) adds
    ~30 instead of ~3000, which had put the array's best start 8 m away (the IVE recovered it or not by chance)."""
    c2 = (DOA_ROBUST * sigma_d) ** 2
    w = None
    for _ in range(iters + 1):
        R, _ = kabsch(u, v, w)
        e = np.sum((np.matmul(u, R.transpose(0, 2, 1)) - v) ** 2, axis=-1)   # (G, n) |R u − v|²
        w = 1.0 / (1.0 + e / c2)
    return R, c2 / (2.0 * sigma_d ** 2) * np.log1p(e / c2).sum(-1)


def doa_cost(u, v, sigma_d):
    """The DOA term of the concentrated cost (G,) that ranks candidate positions: :func:`robust_kabsch`'s at the
    plain Kabsch rotation (no reweighting: one 3 × 3 SVD per point; enough to rank, office seed 10's A4 starts
    0.2 m from its position instead of 8 m; the chosen start's rotation is reweighted, :func:`doa_rotation`)."""
    return robust_kabsch(u, v, sigma_d, iters=0)[1]


def hemisphere_normals(n=200):
    """Quasi-uniform unit vectors (n, 3) on the upper hemisphere (Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_NORMALS = hemisphere_normals()
_NORMALS_COARSE = hemisphere_normals(64)  # ~20° apart: enough to rank a coarse position grid


def unfold_candidates(u, n_a, v, normals=_NORMALS):
    """The two sign patterns that unfold mirror-ambiguous DOAs, for world directions v (G, n, 3).

    A planar array measures u folded to n_a·u >= 0. Its plane normal in the world, ±n_w = ±R n_a, is the
    direction that best explains |n_w·v_j| = n_a·u_j; the sign of n_w·v_j then says which events lie
    behind the plane. Returns (u_plus, u_minus), each (G, n, 3), for R n_a = +n_w and −n_w.
    """
    c = u @ n_a
    proj = (v.reshape(-1, 3) @ normals.T).reshape(v.shape[0], v.shape[1], -1)  # BLAS, not einsum
    h = np.argmin(((np.abs(proj) - c[None, :, None]) ** 2).sum(1), axis=1)
    behind = (np.take_along_axis(proj, h[:, None, None], axis=2)[..., 0] < 0)[..., None]
    ur = mirror(u, n_a)
    return np.where(behind, ur, u), np.where(behind, u, ur)


def doa_rotation(p, st, i, x):
    """Kabsch rotation of array ``i`` placed at ``x`` (a linear board or a pair: the smallest turn of its axis
    onto :func:`cone_cost`'s; identity if it has < 2 DOAs and too few cone rows)."""
    md = p.doa.arr == i
    cones = _cone_rows(p, st, i)
    if md.sum() < 2 and cones is not None:
        a = cone_cost(cones[0], _directions(cones[1], x[None]), float(p.sigma["cone"]))[1][0]
        return Rotation.align_vectors(a[None], p.cone_axis[i][None])[0].as_matrix()   # the smallest turn
    if md.sum() < 2:
        return np.eye(3)
    u, v = p.doa.u[md], _directions(st.s[p.doa.ev[md]], x[None])
    sigma_d = float(p.sigma["doa"])
    if not np.any(p.fold[i]):
        return robust_kabsch(u, v, sigma_d)[0][0]
    fits = [robust_kabsch(uu, v, sigma_d) for uu in unfold_candidates(u, p.fold[i], v)]
    return min(fits, key=lambda f: f[1][0])[0][0]


def _subsample_mask(K, max_events):
    """Boolean (K,): at most ``max_events`` evenly spaced events (all of them if K <= max_events)."""
    if K <= max_events:
        return np.ones(K, bool)
    keep = np.zeros(K, bool)
    keep[np.unique(np.linspace(0, K - 1, max_events).round().astype(int))] = True
    return keep


def grid_events(p, max_events=GRID_MAX_EVENTS):
    """Indices of the events the subsampled grid search names (its events and their TDOA-S partners)."""
    keep = _subsample_mask(p.K, max_events)
    return np.union1d(np.flatnonzero(keep), p.tdoa_s.b[keep[p.tdoa_s.a]])


def event_subsample(p, i, max_events=GRID_MAX_EVENTS):
    """Array ``i``'s measurement rows restricted to at most ``max_events`` evenly spaced events.

    The grid search's cost is (grid points) × (measurements); on a subsample of events it is bounded and
    the initialisation stays linear in the number of events. TDOA-S rows are kept by their ``from`` event
    (their other source is known as well). Returns a :class:`Problem` (``p`` itself if nothing is dropped).
    """
    keep = _subsample_mask(p.K, max_events)
    if keep.all():
        return p
    return p.replace(tdoa_m=p.tdoa_m.select(keep[p.tdoa_m.ev] & (p.tdoa_m.arr == i)),
                     tdoa_s=p.tdoa_s.select(keep[p.tdoa_s.a] & (p.tdoa_s.arr == i)),
                     doa=p.doa.select(keep[p.doa.ev] & (p.doa.arr == i)))


def coarse_candidates(p, st, i, kappa, sigma_d, grid, n_candidates=4):
    """The coarse grid's best local minima for array ``i`` (``p`` its event subsample): points (nc, 3)."""
    step, pts = grid["step"], grid["pts"]
    cost = coarse_cost(p, st, i, kappa, sigma_d, grid)
    # Too close to a source the model is singular; keep candidates at least half a step away.
    cost = np.where(grid["dmin"] > 0.5 * step, cost, np.inf)
    C = cost.reshape(grid["shape"])
    is_min = (C == minimum_filter(C, size=3, mode="nearest")) & np.isfinite(C)
    cand = np.flatnonzero(is_min.ravel())
    cand = cand[np.argsort(cost[cand])][:n_candidates]
    # Zoom only into minima whose concentrated cost is comparable to the best one: in simulations of the
    # paper's protocol a minimum 350+ cost units worse never won, while near-ties do occur.
    cand = cand[cost[cand] <= cost[cand[0]] + max(50.0, 0.5 * abs(cost[cand[0]]))]
    return pts[cand]


def place_arrays(p, st, arrays, kappa, sigma_d, n_candidates=4, zoom_levels=4, grid=None):
    """Position, rotation, offset and drift of each of ``arrays`` (sources fixed): coarse grid → the best
    local minima (:func:`coarse_candidates`) → each zoomed in by successively halved 5×5×5 grids (no
    iterative solver), every array's candidates together (one batched evaluation per level,
    :func:`profile_cost_many`) → the lowest concentrated cost wins. With more than ``GRID_MAX_EVENTS``
    events the search uses an evenly spaced subsample of them (the joint solve refines with all of them).
    ``grid``: :func:`coarse_grid` of the current sources (computed if None). Returns (state with those
    arrays placed, their concentrated costs)."""
    subs, zoomed = _zoomed_minima(p, st, arrays, kappa, sigma_d, n_candidates, zoom_levels, grid)
    out, costs = st.copy(), []
    for q, i, (c, cost, drift, off) in zip(subs, arrays, zoomed):
        g = int(np.argmin(cost))  # the first of equal minima, as a sequential search would keep
        costs.append(float(cost[g]))
        out.x[i], out.R[i] = c[g], doa_rotation(q, st, i, c[g])
        out.drift[i], out.offset[i] = drift[g], off[g]
    return out, costs


def without_cones(p):
    """``p`` without its cone rows (linear boards and pairs placed by their arrivals alone)."""
    return p.replace(cone=p.cone.select(np.zeros(len(p.cone.ev), bool))) if len(p.cone.ev) else p


# A dropped array's bearings may be what held it in its wrong basin (a horizontal planar board whose sources all lie
# near its mic plane reads no elevation: every minimum of its cost with its DOAs lay in that basin, 1 m off), so it
# is placed by its clock rows alone too: its DOA and cone costs scaled away by this factor on their sigma (its
# DOAs then only turn it, by Kabsch)
BEARINGS_BLIND = 1e6


def restart_poses(p, st, i, kappa, sigma_d):
    """Fresh starts for array ``i`` with the sources and the other arrays of ``st`` held (an array the joint
    solve dropped as inconsistent: its refit alone stays in the basin it was solved in): every zoomed local
    minimum of its concentrated cost, with its cone rows (a linear board or a pair) and without, and of its
    clock rows' cost alone (BEARINGS_BLIND), not only the lowest (``ambiguity.retry_dropped`` refits each on
    all the array's rows and keeps the best)."""
    out = placed_poses(p, st, i, kappa, sigma_d) + placed_poses(p, st, i, kappa, BEARINGS_BLIND * sigma_d)
    return out + placed_poses(without_cones(p), st, i, kappa, sigma_d) if len(p.cone.ev) else out


def placed_poses(p, st, i, kappa, sigma_d, n_candidates=4, zoom_levels=4):
    """Every zoomed local minimum of array ``i``'s concentrated cost (sources and the other arrays of ``st``
    held), not only the lowest: states with array ``i`` placed there."""
    subs, [(c, _, drift, off)] = _zoomed_minima(p, st, [i], kappa, sigma_d, n_candidates, zoom_levels, None)
    out = []
    for g in range(len(c)):
        alt = st.copy()
        alt.x[i], alt.R[i] = c[g], doa_rotation(subs[0], st, i, c[g])
        alt.drift[i], alt.offset[i] = drift[g], off[g]
        out.append(alt)
    return out


def _zoomed_minima(p, st, arrays, kappa, sigma_d, n_candidates, zoom_levels, grid):
    """(each array's event subsample, per array (points (nc, 3), concentrated cost, drift, offset (nc,)) of its
    coarse minima each zoomed in ``zoom_levels`` times): :func:`place_arrays`'s search."""
    grid = coarse_grid(st.s, grid_events(p)) if grid is None else grid
    subs = [event_subsample(p, i) for i in arrays]
    centres = [coarse_candidates(q, st, i, kappa, sigma_d, grid, n_candidates) for q, i in zip(subs, arrays)]
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    h, no = grid["step"], len(offsets)
    rows = [(_clock_rows(q, st, i), _doa_rows(q, st, i)) for q, i in zip(subs, arrays)]
    for _ in range(zoom_levels):
        h *= 0.5
        pts = [(c[:, None, :] + h * offsets[None]).reshape(-1, 3) for c in centres]
        out = profile_cost_many([(q, i, x) for q, i, x in zip(subs, arrays, pts)], st, kappa, sigma_d, rows=rows)
        ends = np.cumsum([len(x) for x in pts])[:-1]
        res = [[z.reshape(-1, no) for z in zs] for zs in zip(*(np.split(o, ends) for o in out))]
        ks = [np.argmin(c_sub, axis=1) for c_sub, _, _ in res]
        centres = [x.reshape(-1, no, 3)[np.arange(len(k)), k] for x, k in zip(pts, ks)]
    zoomed = []
    for c, (c_sub, d_sub, o_sub), k in zip(centres, res, ks):
        m = np.arange(len(k))
        zoomed.append((c, c_sub[m, k], d_sub[m, k], o_sub[m, k]))
    return subs, zoomed


def initialise(p):
    """Deterministic initial state for the whole problem. Returns (state, info dict)."""
    best = None
    for sources in init_sources(p):
        st = empty_state(p)
        st.s = sources
        st, info_ref, q, lay = refine_reference(p, st)
        if best is None or info_ref["cost"] < best[1]["cost"]:
            best = (st, info_ref, q, lay)
    st, info_ref, q, lay = best
    sig_src = source_spread(q, st, lay)
    dist = np.median(np.linalg.norm(st.s, axis=1))
    kappa = max(3.0 * p.sigma["tdoa_m"], 2.0 * sig_src / p.c)
    sigma_d = float(np.hypot(p.sigma["doa"], sig_src / max(dist, 0.1)))
    grid = coarse_grid(st.s, grid_events(p))  # the sources stay fixed while the arrays are placed
    arrays = [i for i in range(p.N) if i != p.ref]
    # by their arrivals and 3-D DOAs: the cone rows rank the coarse grid's minima differently and, from the
    # reference array's sources alone, no better (a pair 4 -> 37 cm off in one of ten scenes); the cone-aware
    # search restarts an array the joint solve dropped (:func:`restart_poses`)
    st, placed = place_arrays(without_cones(p), st, arrays, kappa, sigma_d, grid=grid)
    costs = {p.names[i]: c for i, c in zip(arrays, placed)}
    return st, {"source_sigma": sig_src, "array_costs": costs, "reference_iterations": info_ref["iterations"]}


# --------------------------------------------------------------------------------------- fold basins
FOLD_NEAR_PLANE_DEG = 20.0  # a planar array whose sources all lie this close to its mic plane has two basins
FOLD_DCOST = 4.5            # an alternative basin within this cost (½ Δχ² = 3σ²/2) is not excluded by the data
FOLD_MIN_DEG = 2.0          # ... if it is another basin: its orientation this far from the solution's


def _rot(axis, angle):
    """Rotation matrix about unit ``axis`` by ``angle`` (rad), Rodrigues."""
    k = np.asarray(axis, float)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def fold_candidates(p, st, i):
    """Other starting orientations of a mirror-ambiguous planar array ``i`` whose sources lie within
    FOLD_NEAR_PLANE_DEG of its mic plane: folded DOAs only tell each source's |elevation|, so a tilt that
    turns the elevations' mean e into −e (about the in-plane axis across the sources' mean direction, by
    ∓2e) fits them too, and so may the orientations that put every source on one side of the plane (the
    measured DOAs, or their mirror images, fitted to the directions: :func:`kabsch`). Returns a list of
    rotation matrices, none within 1° of the solution's or of each other (empty when the array is not in
    that case)."""
    m = p.doa.arr == i
    if i == p.ref or not np.any(p.fold[i]) or not p.rot_free[i] or m.sum() < 3:
        return []
    n = st.R[i] @ p.fold[i]
    w = st.s[p.doa.ev[m]] - st.x[i]
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    elev = np.arcsin(np.clip(w @ n, -1, 1))
    if np.max(np.abs(elev)) > np.deg2rad(FOLD_NEAR_PLANE_DEG):
        return []
    mean_dir = w.mean(axis=0) - (w.mean(axis=0) @ n) * n
    if np.linalg.norm(mean_dir) < 1e-6:
        return []
    k = np.cross(n, mean_dir / np.linalg.norm(mean_dir))
    e = float(np.mean(elev))
    tilts = [_rot(k, a) @ st.R[i] for a in (2 * e, -2 * e)]
    # every source on one side of the mic plane, then every one on the other (the DOAs as measured, or mirrored
    # across the plane, fitted to the directions): a solution whose plane cuts through the sources (tilted about
    # their mean direction, where e ≈ 0) has no tilt across it to the true basin
    u = p.doa.u[m]
    sides = [kabsch(uu, w)[0] for uu in (u, mirror(u, p.fold[i]))]
    out = []
    for R in tilts + sides:
        if all(_angle_deg(R, Q) > 1.0 for Q in [st.R[i]] + out):
            out.append(R)
    return out


def fold_basins(p, st, lay, kinds, mask, max_iter=200):
    """Try each planar array's other fold basin (:func:`fold_candidates`), re-solved by least squares from
    there (the final mask). The lower cost is reported (a lower basin: the solve had started in the wrong one);
    one within FOLD_DCOST (and FOLD_MIN_DEG away) is not excluded by the data, whichever is reported
    (``verdict.fold_ambiguity`` names the array, its std covers the other). Unlike a mirror solution
    (``ambiguity.mirror_basins``) the cost difference alone decides: the two basins' Δχ² follows its
    linear-Gaussian law ±δ² ± 2δ (δ²: ``ambiguity.separation``, recorded), so ½ Δχ² ≥ FOLD_DCOST is 3σ-safe
    at any δ (169 basin pairs with δ² < 100 of feature-level scenes: (Δχ² − δ²)/2δ std 0.89, |max| 3.0;
    docs/method.md).
    Returns (state, records): one {array, dcost, separation_chi2, rotation_deg, position_m, displacement_m,
    rotvec, switched, ambiguous} per candidate (one that slides into a basin already tried: none); dcost is the other basin's cost minus the solution's before
    the switch, displacement_m and rotvec (array frame) go from the reported basin to the other one."""
    cands = {i: fold_candidates(p, st, i) for i in range(p.N) if np.any(p.fold[i])}
    if not any(cands.values()):
        return st, []
    cost0 = linearise(p, st, lay, kinds, mask=mask).cost
    records = []
    for i in cands:
        found = [st.R[i]]
        for R in fold_candidates(p, st, i):
            alt = st.copy()
            alt.R[i] = R
            alt, _ = levenberg_marquardt(p, alt, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
            if any(_angle_deg(Q, alt.R[i]) < FOLD_MIN_DEG for Q in found[1:]):
                continue   # a basin already tried
            found.append(alt.R[i])
            rec = _fold_record(p, st, alt, lay, kinds, mask, i, cost0)
            records.append(rec)
            if rec["switched"]:
                st, cost0 = alt, cost0 + rec["dcost"]
    return st, records


def _angle_deg(Ra, Rb):
    """The angle (deg) of the rotation between orientations ``Ra`` and ``Rb``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def _fold_record(p, st, alt, lay, kinds, mask, i, cost0):
    """Array ``i``'s other fold basin ``alt`` against the solution ``st`` (:func:`fold_basins`' record)."""
    dR = st.R[i].T @ alt.R[i]
    dcost = float(linearise(p, alt, lay, kinds, mask=mask).cost - cost0)
    rotation = _angle_deg(st.R[i], alt.R[i])
    apart = rotation >= FOLD_MIN_DEG   # (the refit may have slid back into the solution's basin)
    ambiguous = bool(apart and abs(dcost) < FOLD_DCOST)
    switched = bool(apart and dcost < 0.0)   # the lower cost is reported, decided or not
    sign = -1.0 if switched else 1.0         # from the reported basin to the other one
    sep = separation(p, st, alt, lay, kinds, mask) if apart else 0.0
    return {"array": str(p.names[i]), "dcost": dcost, "separation_chi2": sep,
            "rotation_deg": rotation, "position_m": float(np.linalg.norm(alt.x[i] - st.x[i])),
            "displacement_m": (sign * (alt.x[i] - st.x[i])).tolist(),   # (uncertainty.cover_alternative)
            "rotvec": (sign * Rotation.from_matrix(dR).as_rotvec()).tolist(), "switched": switched,
            "ambiguous": ambiguous}
