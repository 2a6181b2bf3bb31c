"""Levenberg–Marquardt on the product manifold (R^n × SO(3)^N) with an optional robust loss.

The robust loss applies to the factors flagged ``robust`` (the TDOAs) and is minimised by iteratively
reweighted least squares inside LM: each iteration linearises, weights each robust residual by
ρ'(r)/(2r) and solves the damped, Jacobi-scaled normal equations. Deterministic: no random restarts.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

from .factors import evaluate
from .problem import retract


def rho(r, loss, k):
    """Robust cost ρ(r) (so that ρ(r) = r² near 0) and IRLS weight ρ'(r)/(2r), elementwise."""
    if loss is None or loss == "linear":
        return r * r, np.ones_like(r)
    a = np.abs(r)
    if loss == "huber":
        small = a <= k
        return np.where(small, r * r, 2 * k * a - k * k), np.where(small, 1.0, k / np.maximum(a, 1e-300))
    if loss == "cauchy":
        z = (r / k) ** 2
        return k * k * np.log1p(z), 1.0 / (1.0 + z)
    raise ValueError(f"unknown loss {loss!r}")


def linearise(p, st, lay, kinds, loss=None, k=3.0, mask=None):
    """Stack the factors: residuals r, Jacobian J, IRLS weights w, per-residual kind labels and cost.

    ``mask`` maps factor kind → boolean array over that factor's residuals (False = excluded outlier).
    """
    fs = evaluate(p, st, lay, kinds)
    r_all, J_all, w_all, cost = [], [], [], 0.0
    for f in fs:
        r, J = f["r"], f["J"]
        keep = np.ones(len(r), bool) if mask is None or f["kind"] not in mask else mask[f["kind"]]
        rr = np.where(keep, r, 0.0)
        c, w = rho(rr, loss if f["robust"] else None, k)
        w = np.where(keep, w, 0.0)
        cost += 0.5 * float(np.sum(np.where(keep, c, 0.0)))
        r_all.append(rr)
        J_all.append(J)
        w_all.append(w)
    return np.concatenate(r_all), np.vstack(J_all), np.concatenate(w_all), cost, fs


def cost_of(p, st, lay, kinds, loss=None, k=3.0, mask=None):
    return linearise(p, st, lay, kinds, loss, k, mask)[3]


def _solve_damped(H, g, lam):
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    A = Hs + lam * np.eye(len(d))
    try:
        step = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(A, check_finite=False), g / d, check_finite=False)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        step = -np.linalg.lstsq(A, g / d, rcond=None)[0]
    return step / d


def levenberg_marquardt(p, st, lay, kinds, *, loss=None, k=3.0, mask=None, max_iter=200, rtol=1e-12,
                        lam0=1e-4):
    """Minimise ½ Σ ρ(r) over the free parameters of ``lay``. Returns (state, info)."""
    if lay["n"] == 0:
        return st, {"iterations": 0, "cost": cost_of(p, st, lay, kinds, loss, k, mask), "converged": True,
                    "reason": "no free parameters"}
    lam, nu = lam0, 2.0
    r, J, w, cost, _ = linearise(p, st, lay, kinds, loss, k, mask)
    reason, it = "max_iter", 0
    for it in range(1, max_iter + 1):
        Jw = J * w[:, None]
        H = J.T @ Jw
        g = Jw.T @ r
        if np.max(np.abs(g) / np.sqrt(np.maximum(np.diag(H), 1e-300))) < 1e-10 * max(1.0, np.sqrt(cost)):
            reason = "gradient"
            break
        accepted = False
        for _ in range(30):
            step = _solve_damped(H, g, lam)
            cand = retract(st, lay, step)
            r2, J2, w2, cost2, _ = linearise(p, cand, lay, kinds, loss, k, mask)
            pred = -(step @ g) - 0.5 * step @ (H @ step)
            ratio = (cost - cost2) / pred if pred > 0 else -1.0
            if cost2 < cost and np.isfinite(cost2):
                accepted = True
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            reason = "no decrease"
            break
        lam *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3) if ratio > 0 else 2.0
        nu = 2.0
        dec = cost - cost2
        st, r, J, w, cost = cand, r2, J2, w2, cost2
        if dec <= rtol * max(cost, 1e-30):
            reason = "cost"
            break
    # "no decrease": no damped step lowers the cost any more, i.e. a numerical minimum.
    return st, {"iterations": it, "cost": cost, "converged": reason != "max_iter", "reason": reason}
