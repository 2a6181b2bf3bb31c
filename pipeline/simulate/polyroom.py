"""Extruded polygonal rooms (non-convex floor plans) and attenuating obstacles for the room simulator.

A room is a floor plan (P, 2) m (corners counter-clockwise, any simple polygon: an L-shaped office, a
U-shaped lab) extruded to ``height``: P vertical walls (wall w joins corner w to corner w + 1), then the floor
and the ceiling (walls P, P + 1). Image sources (Allen & Berkley / Borish): an image is reflected across
every wall it lies in front of, up to ``max_order`` reflections; each image is an AFFINE function of the
source position, ``p_k(s) = M_k s + b_k`` (``M_k`` a product of Householder reflections), so a moving
source's images follow it exactly. Visibility is checked per image and microphone by backtracking the path
(Borish 1984): the segment from the mic to the image must cross its last wall's face, and every leg of the
unfolded path must cross no other wall. In a non-convex room this removes the direct path (and the
reflections) that walls block: only what can physically arrive is rendered.

Obstacles are vertical rectangles (a cabinet, a partition, a shelf: a floor segment ``p0``–``p1`` and a
height range) that do not reflect but attenuate every path leg crossing them by a per-octave-band loss
(transmission and diffraction lose more at high frequency). Their loss is applied to the direct path and to
reflections alike.
"""
from __future__ import annotations

import numpy as np

EPS = 1e-9           # relative tolerance of the segment parameters (a leg touching its own wall is not blocked)


# ----------------------------------------------------------------------------------------------- geometry
def make_geometry(floor_plan, height, obstacles=()):
    """The room as a dict: ``corners`` (P, 2), ``height``, ``normal`` (W, 3) inward unit normals and
    ``offset`` (W,) (plane ``normal · x = offset``), ``area`` (W,) m², ``volume`` m³, ``obstacles`` (list of
    dicts with ``p0``, ``p1`` (2,), ``z`` (2,), ``loss_db`` (7,))."""
    c = np.asarray(floor_plan, float)
    if signed_area(c) < 0:
        c = c[::-1].copy()                                    # counter-clockwise: inward normal on the left
    e = np.roll(c, -1, axis=0) - c
    length = np.linalg.norm(e, axis=1)
    n2 = np.stack([-e[:, 1], e[:, 0]], axis=1) / length[:, None]
    normal = np.concatenate([np.column_stack([n2, np.zeros(len(c))]), [[0, 0, 1.0], [0, 0, -1.0]]])
    offset = np.r_[np.sum(n2 * c, axis=1), 0.0, -float(height)]
    floor = signed_area(c)
    return {"corners": c, "height": float(height), "normal": normal, "offset": offset,
            "area": np.r_[length * height, floor, floor], "volume": floor * height,
            "obstacles": [{"p0": np.asarray(o["p0"], float), "p1": np.asarray(o["p1"], float),
                           "z": np.asarray(o["z"], float), "loss_db": np.asarray(o["loss_db"], float)}
                          for o in obstacles]}


def signed_area(c):
    """Shoelace area of a polygon (P, 2), positive when counter-clockwise."""
    x, y = np.asarray(c, float).T
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def inside(geo, p, margin=0.0):
    """(n,) bool: points (n, 3) inside the room, at least ``margin`` m from every wall."""
    p = np.atleast_2d(p)
    ok = inside_polygon(geo["corners"], p[:, :2]) & (p[:, 2] >= margin) & (p[:, 2] <= geo["height"] - margin)
    if margin > 0:
        ok &= _edge_distance(geo["corners"], p[:, :2]) >= margin
    return ok


def inside_polygon(c, xy):
    """(...,) bool: ray casting, points ``xy`` (..., 2) inside the polygon ``c`` (P, 2)."""
    x, y = xy[..., 0, None], xy[..., 1, None]
    a, b = c, np.roll(c, -1, axis=0)
    cross = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xs = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.sum(cross & (x < xs), axis=-1) % 2) == 1


def _edge_distance(c, xy):
    a, b = c, np.roll(c, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("nkd,kd->nk", xy[:, None] - a, ab) / np.sum(ab * ab, axis=1), 0, 1)
    return np.min(np.linalg.norm(xy[:, None] - (a + t[..., None] * ab), axis=2), axis=1)


# ----------------------------------------------------------------------------------------------- images
def image_tree(geo, src, max_order):
    """Image sources of ``src`` (3,) up to ``max_order`` reflections: a dict of arrays over images (n):
    ``pos`` (n, 3), ``M`` (n, 3, 3), ``b`` (n, 3) (``pos = M src + b``), ``parent`` (n,) (−1 for the real
    source), ``wall`` (n,) last wall (−1), ``order`` (n,), ``hits`` (n, W) reflections per wall, ``direct``."""
    W = len(geo["normal"])
    pos, M, b = [np.asarray(src, float)], [np.eye(3)], [np.zeros(3)]
    parent, wall, order, hits = [-1], [-1], [0], [np.zeros(W, int)]
    level = [0]
    for o in range(1, max_order + 1):
        nxt = []
        for k in level:
            for w in range(W):
                n, d = geo["normal"][w], geo["offset"][w]
                if w == wall[k] or n @ pos[k] - d <= 0:       # only images in front of the wall reflect in it
                    continue
                H = np.eye(3) - 2 * np.outer(n, n)
                pos.append(H @ pos[k] + 2 * d * n)
                M.append(H @ M[k])
                b.append(H @ b[k] + 2 * d * n)
                parent.append(k), wall.append(w), order.append(o)
                h = hits[k].copy()
                h[w] += 1
                hits.append(h)
                nxt.append(len(pos) - 1)
        level = nxt
    out = {"pos": np.array(pos), "M": np.array(M), "b": np.array(b), "parent": np.array(parent),
           "wall": np.array(wall), "order": np.array(order), "hits": np.array(hits)}
    out["direct"] = out["order"] == 0
    return out


def moved(tree, src):
    """Image positions (n, 3) of the same reflection paths for the source at ``src`` (3,)."""
    return tree["M"] @ np.asarray(src, float) + tree["b"]


# ----------------------------------------------------------------------------------------------- visibility
def path_gains(geo, tree, mics, pos=None, n_bands=7, only=None):
    """Per image, mic and band the gain of the geometric path (n, M, B): 0 where a wall blocks it (or the
    path misses its wall's face), the obstacles' losses where it crosses them, else 1.

    pos : image positions (n, 3) (default ``tree['pos']``; pass :func:`moved` for another source position).
    only : optional (n,) bool, the images to evaluate (the others get 0).
    """
    pos = tree["pos"] if pos is None else pos
    mics = np.asarray(mics, float)
    n, m = len(pos), len(mics)
    gain = np.zeros((n, m, n_bands))
    for o in np.unique(tree["order"]):
        idx = np.flatnonzero((tree["order"] == o) & (True if only is None else only))
        if idx.size == 0:
            continue
        q = np.broadcast_to(mics, (idx.size, m, 3)).copy()
        ok = np.ones((idx.size, m), bool)
        g = np.ones((idx.size, m, n_bands))
        cur = idx
        for _ in range(o):
            x, hit = _face_hit(geo, q, pos[cur], tree["wall"][cur])
            ok &= hit & ~_blocked(geo, q, x)
            g *= _obstacle_gain(geo, q, x, n_bands)
            q, cur = x, tree["parent"][cur]
        src = np.broadcast_to(pos[cur][:, None, :], q.shape)
        ok &= ~_blocked(geo, q, src)
        g *= _obstacle_gain(geo, q, src, n_bands)
        gain[idx] = np.where(ok[..., None], g, 0.0)
    return gain


def _face_hit(geo, q, target, wall):
    """Where the legs ``q`` (n, M, 3) → ``target`` (n, 3) cross the plane of ``wall`` (n,), and whether
    that point is on the wall's face, strictly between the ends."""
    nrm, off = geo["normal"][wall], geo["offset"][wall]
    d = target[:, None, :] - q
    den = np.einsum("nmd,nd->nm", d, nrm)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (off[:, None] - np.einsum("nmd,nd->nm", q, nrm)) / den
    finite = np.isfinite(t)
    t = np.where(finite, t, 0.0)
    x = q + t[..., None] * d
    hit = finite & (t > EPS) & (t < 1 - EPS)
    P = len(geo["corners"])
    vert = wall < P
    c = geo["corners"]
    a, b = c[np.where(vert, wall, 0)], c[(np.where(vert, wall, 0) + 1) % P]
    ab = b - a
    u = np.einsum("nmd,nd->nm", x[..., :2] - a[:, None], ab) / np.sum(ab * ab, axis=1)[:, None]
    z = x[..., 2]
    on_vertical = (u >= -EPS) & (u <= 1 + EPS) & (z >= 0) & (z <= geo["height"])
    on_flat = inside_polygon(c, x[..., :2])
    return x, hit & np.where(vert[:, None], on_vertical, on_flat)


def _crossings(p, q, a, b):
    """Segment parameters of the crossings of legs p → q (..., 2) with segments a → b (E, 2): (t, u), each
    (..., E), NaN where parallel."""
    r, s = q - p, b - a
    den = r[..., None, 0] * s[:, 1] - r[..., None, 1] * s[:, 0]
    ap = a - p[..., None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ap[..., 0] * s[:, 1] - ap[..., 1] * s[:, 0]) / den
        u = (ap[..., 0] * r[..., None, 1] - ap[..., 1] * r[..., None, 0]) / den
    return t, u


def _blocked(geo, p, q):
    """(...,) bool: the open leg p → q (..., 3) crosses a vertical wall (legs stay between floor and
    ceiling, so only vertical walls can block them)."""
    c = geo["corners"]
    t, u = _crossings(p[..., :2], q[..., :2], c, np.roll(c, -1, axis=0))
    return np.any((t > 1e-7) & (t < 1 - 1e-7) & (u >= -1e-7) & (u <= 1 + 1e-7), axis=-1)


def _obstacle_gain(geo, p, q, n_bands):
    """(..., B) product of the band gains of the obstacles the legs p → q cross."""
    g = np.ones(p.shape[:-1] + (n_bands,))
    for ob in geo["obstacles"]:
        t, u = _crossings(p[..., :2], q[..., :2], ob["p0"][None], ob["p1"][None])
        t, u = t[..., 0], u[..., 0]
        z = p[..., 2] + np.where(np.isfinite(t), t, 0.0) * (q[..., 2] - p[..., 2])
        cross = (t > 0) & (t < 1) & (u >= 0) & (u <= 1) & (z >= ob["z"][0]) & (z <= ob["z"][1])
        g = np.where(cross[..., None], g * 10 ** (-ob["loss_db"] / 20), g)
    return g


def direct_gain(geo, src, points):
    """(n, B) gain of the direct path from ``src`` (3,) to ``points`` (n, 3): 0 behind a wall, the
    obstacles' losses, else 1 (the line-of-sight truth)."""
    p = np.atleast_2d(np.asarray(points, float))
    s = np.broadcast_to(np.asarray(src, float), p.shape)
    g = _obstacle_gain(geo, p, s, 7)
    return np.where(_blocked(geo, p, s)[:, None], 0.0, g)
