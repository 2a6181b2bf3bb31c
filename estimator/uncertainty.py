"""Uncertainty: covariance (JᵀWJ)⁻¹ with the gauge fixed by the reference array, and the CRLB.

The same machinery serves both: at the estimate it gives the ``*_std`` columns, at ground truth the
Cramér–Rao lower bound for unbiased estimators under the stated Gaussian noise.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .factors import ALL_KINDS
from .problem import build_problem, empty_state, make_layout, retract
from .solver import linearise


def covariance(J, lay_n):
    """(JᵀJ)⁻¹ for whitened residuals (Jacobi-scaled for conditioning)."""
    d = np.linalg.norm(J, axis=0)
    d = np.where(d > 0, d, 1.0)
    Js = J / d
    return np.linalg.pinv(Js.T @ Js) / d[:, None] / d[None, :]


def std_from_cov(p, lay, cov):
    """1-σ std per parameter, as arrays keyed like the state (NaN where fixed)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))

    def pick(idx):
        return np.where(idx >= 0, sd[np.maximum(idx, 0)], np.nan)

    return {"x": pick(lay["x"]), "rot": pick(lay["rot"]), "offset": pick(lay["offset"]),
            "drift": pick(lay["drift"]), "s": pick(lay["s"]), "e": pick(lay["e"])}


def state_from_frames(p, arrays, sources=None):
    """State dict from arrays/sources DataFrames (e.g. truth), ordered as the problem's arrays/events.

    Unknown (NaN) offsets or drifts become 0.
    """
    st = empty_state(p)
    a = arrays.set_index("array").loc[list(p["names"])]
    st["x"] = a[["x", "y", "z"]].to_numpy(float)
    st["R"] = Rotation.from_quat(a[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True).as_matrix()
    st["offset"] = np.nan_to_num(a["offset"].to_numpy(float))
    st["drift"] = np.nan_to_num(a["drift"].to_numpy(float))
    if sources is not None:
        s = sources.set_index("event").loc[list(p["events"])]
        st["s"] = s[["x", "y", "z"]].to_numpy(float)
    return st


def fisher(p, st, kinds=None):
    """Fisher information JᵀJ of the whitened residuals at ``st`` and its layout."""
    lay = make_layout(p)
    kinds = kinds or [k for k in ALL_KINDS if k != "emission" or p["sigma_emit"] > 0]
    _, J, _, _, _ = linearise(p, st, lay, kinds)
    return J, lay


def crlb(features, truth, *, use_tdoa_s=True, emission_sigma=0.0):
    """Cramér–Rao bound at ground truth.

    Returns dict: ``cov`` (n, n) over the free parameters, ``layout``, ``std`` (per-parameter 1-σ keyed
    like the state: x (N,3) m, rot (N,3) rad, offset (N,) s, drift (N,), s (K,3) m, e (K,) s),
    ``problem`` and ``state`` (the truth state).
    """
    p = build_problem(features, use_tdoa_s=use_tdoa_s, sigma_emit=emission_sigma)
    st = state_from_frames(p, truth["arrays"], truth.get("sources"))
    J, lay = fisher(p, st)
    cov = covariance(J, lay["n"])
    return {"cov": cov, "layout": lay, "std": std_from_cov(p, lay, cov), "problem": p, "state": st}


def draw_from_crlb(bound, rng):
    """One estimate drawn from N(truth, CRLB) as a state (rotations perturbed on the manifold)."""
    cov = bound["cov"]
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    delta = V @ (np.sqrt(np.maximum(w, 0.0)) * rng.standard_normal(len(w)))
    return retract(bound["state"], bound["layout"], delta)
