"""Geometry and clock formulas every layer shares (one place each; docs/architecture.md).

- :func:`mirror` / :func:`fold`: the mirror image of directions across a plane (planar arrays measure DOAs
  up to that image) and the fold onto the plane's positive side.
- :func:`mic_geometry` / :func:`plane_normal`: what an array's mics can measure (single, linear, planar,
  volume) and a planar array's normal.
- :func:`doa_covariance`: the shape of a plane-wave DOA's error covariance from the mics' layout (a planar
  array's elevation error grows as the source nears its plane).
- :func:`yaw_matrix` / :func:`yaw_rotate`: the rotation ``Rz(ψ)`` about the vertical axis.
- :func:`local_time` / :func:`arrival_time`: the clock model ``L_i(t) = (1 + δ_i)(t − t_0) + τ_i`` and the
  arrival ``a_ij = L_i(t_j + |s_j − x_i| / c) + β δ_i`` (β: the chirp's drift bias).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Values = float | NDArray  # a number, or an array that broadcasts against the others


def _dot(u, n):
    """u·n over the last axis: one normal (3,) for all (BLAS), or one per row (..., 3)."""
    return u @ n if np.ndim(n) == 1 else np.einsum("...a,...a->...", u, n)


def mirror(u: NDArray, n: NDArray, origin: NDArray | None = None) -> NDArray:
    """Mirror image ``u − 2 ((u − origin)·n) n`` of points or directions u (..., 3) across the plane with
    unit normal n ((3,) or one per row (..., 3)) through ``origin`` (3,) (default: through 0)."""
    d = _dot(u if origin is None else u - origin, n)
    return u - 2.0 * d[..., None] * n


def fold(u: NDArray, n: NDArray) -> NDArray:
    """Directions u (..., 3) folded onto the side n·u >= 0 of the plane with unit normal n ((3,) or (..., 3)):
    the mirror image where n·u < 0, u elsewhere."""
    d = _dot(u, n)
    return np.where((d < 0)[..., None], u - 2.0 * d[..., None] * n, u)


MIC_GEOMETRY_TOL = 1e-3   # m: RMS spread of the mics off a line / plane below which they lie on it


def mic_geometry(mics: ArrayLike, tol: float = MIC_GEOMETRY_TOL) -> tuple[str, NDArray | None]:
    """What the array's geometry lets it measure: (kind, vector).

    kind: "single" (1 mic: no direction), "linear" (collinear mics, 2-mic pairs: the angle to the axis;
    vector = the unit axis in the array frame, sign such that its largest component is positive, snapped
    to a coordinate axis when within 1e-9), "planar" (vector = the unit normal of the mic plane) or
    "volume" (full direction; vector None).
    """
    mics = np.asarray(mics, float)
    if len(mics) < 2:
        return "single", None
    d = mics - mics.mean(axis=0)
    _, sv, vt = np.linalg.svd(d, full_matrices=True)
    sv = np.r_[sv, np.zeros(3 - len(sv))] / np.sqrt(len(mics))
    if sv[1] < tol:
        a = vt[0] * np.sign(vt[0][np.argmax(np.abs(vt[0]))])
        k = int(np.argmax(np.abs(a)))
        if a[k] > 1 - 1e-9:
            a = np.eye(3)[k]
        return "linear", a
    if sv[2] < tol:
        return "planar", vt[2]
    return "volume", None


def steered_doas(u: ArrayLike, ratio: float, normal: ArrayLike | None = None,
                 axis: ArrayLike | None = None) -> NDArray:
    """The DOAs (n, 3) a steered-response frontend reports for true directions ``u`` (n, 3) when it steers with
    ``ratio`` = c_steered / c_true (docs/method.md, "The DOAs' speed of sound").

    A planar array (unit mic-plane ``normal``) sees only the in-plane part v of u through its delays v·m / c,
    so its peak lies at ratio·v, and the frontend completes it to u' = ratio·v + √(1 − ratio²|v|²) n on u's
    side of the plane (in the plane, ratio·v / |ratio·v|, past |ratio·v| = 1: frontend.doa._refine_planar).
    A linear array (unit ``axis``) measures cos θ = a·u through the same delays: ratio·cos θ (clipped), here
    returned as u with its axial part scaled and the rest renormalised. A 3-D array: u (its best unit
    direction is unchanged by a scale)."""
    u = np.asarray(u, float)
    if normal is not None:
        n = np.asarray(normal, float)
        a = _dot(u, n)
        x = ratio * (u - a[..., None] * n)
        r = np.linalg.norm(x, axis=-1)
        up = np.sqrt(np.clip(1.0 - r * r, 0.0, None)) * np.where(a < 0, -1.0, 1.0)
        inside = (r <= 1.0)[..., None]
        return np.where(inside, x + up[..., None] * n, x / np.maximum(r, 1e-12)[..., None])
    if axis is not None:
        ax = np.asarray(axis, float)
        cos = _dot(u, ax)
        rest = u - cos[..., None] * ax
        cn = np.clip(ratio * cos, -1.0, 1.0)
        rn = np.linalg.norm(rest, axis=-1)
        perp = np.where((rn > 1e-12)[..., None], rest / np.maximum(rn, 1e-12)[..., None], _any_perp(ax))
        return cn[..., None] * ax + np.sqrt(1.0 - cn * cn)[..., None] * perp
    return u


def _any_perp(a):
    """A unit vector perpendicular to the unit vector ``a`` (3,)."""
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    v = e - (e @ a) * a
    return v / np.linalg.norm(v)


def plane_normal(mics: ArrayLike) -> NDArray | None:
    """Unit normal (3,) of a planar array's mic plane (:func:`mic_geometry`), None for any other geometry."""
    kind, v = mic_geometry(mics)
    return v if kind == "planar" else None


def doa_covariance(u: NDArray, mics: ArrayLike, normal: NDArray | None = None, floor: Values = 0.0) -> NDArray:
    """(J, 3, 3) covariance of plane-wave DOAs u (J, 3) (array frame) per unit variance of the mic positions'
    projections (m²/s² · s²: multiply by c² σ_t² for one mic's timing variance σ_t²): ``P S⁺ Pᵀ``, S the
    scatter of the mic positions about their centre. A volume array (``normal`` None): P = I − u uᵀ. A planar
    array (unit ``normal`` n) measures only the in-plane part v of u; the normal part √(1 − |v|²) follows
    with P = I − n vᵀ / |u·n| (n on u's side), so the error along the elevation grows as 1/|u·n| while the azimuth's does
    not (|u·n| floored at ``floor``, where the linearisation ends)."""
    u = np.asarray(u, float)
    d = np.asarray(mics, float)
    d = d - d.mean(axis=0)
    s_pinv = np.linalg.pinv(d.T @ d)
    if normal is None:
        p = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
    else:
        nrm = np.asarray(normal, float)
        h = u @ nrm
        v = u - h[:, None] * nrm
        side = np.where(h < 0, -1.0, 1.0)[:, None] * nrm           # the normal on u's side of the plane
        p = np.eye(3)[None] - side[:, :, None] * v[:, None, :] / np.maximum(np.abs(h), floor)[:, None, None]
    return p @ s_pinv @ np.transpose(p, (0, 2, 1))


def yaw_matrix(psi: float) -> NDArray:
    """(3, 3) rotation ``Rz(ψ)`` by ψ (rad) about z (counter-clockwise seen from +z)."""
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_rotate(v: NDArray, psi: ArrayLike) -> NDArray:
    """``Rz(ψ) v`` for vectors v (..., 3), written out (no matrix product) so it vectorises over yaws:
    ψ a scalar gives v's shape; ψ (Y,) gives (Y, ..., 3)."""
    psi = np.asarray(psi, float)
    c, s = np.cos(psi), np.sin(psi)
    if psi.ndim:
        c, s = (a.reshape(a.shape + (1,) * (v.ndim - 1)) for a in (c, s))
    x, y = c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]
    return np.stack([x, y, np.broadcast_to(v[..., 2], x.shape)], axis=-1)


def local_time(t: ArrayLike, offset: Values, drift: Values, t0: float = 0.0) -> NDArray:
    """Array clock reading ``L(t) = (1 + δ)(t − t0) + τ`` (s) at true (emitter) time(s) t (s).

    offset τ (s) and drift δ broadcast against t; t0: the first emission (the clocks' common origin).
    """
    return (1.0 + drift) * (np.asarray(t, float) - t0) + offset


def arrival_time(t_emit: ArrayLike, dist: Values, offset: Values, drift: Values, c: float,
                 beta: float = 0.0, t0: float = 0.0) -> NDArray:
    """Local-clock arrival ``a = L(t_emit + dist / c) + β δ`` (s) of a chirp emitted at t_emit (s) travelling
    dist (m) at c (m/s); β (s per unit drift): the matched filter's drift bias of the chirp."""
    return local_time(np.asarray(t_emit, float) + dist / c, offset, drift, t0) + beta * drift
