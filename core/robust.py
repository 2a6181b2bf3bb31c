"""Robust scale: the median absolute deviation scaled to a normal standard deviation (one place)."""
from __future__ import annotations

import numpy as np
from scipy.special import ndtri

# MAD × this = σ for normal data: 1 / Φ⁻¹(3/4) ≈ 1.4826 (the constant scipy's median_abs_deviation uses)
MAD_TO_SIGMA = float(1.0 / ndtri(0.75))


def mad_std(x, axis=None, center=None):
    """Robust standard deviation ``MAD_TO_SIGMA · median |x − center|`` (NaN ignored).

    x : array; axis : as numpy's; center : the median of ``x`` along ``axis`` when None (broadcastable)."""
    x = np.asarray(x, float)
    if center is None:
        center = np.nanmedian(x, axis=axis, keepdims=True)
    return MAD_TO_SIGMA * np.nanmedian(np.abs(x - center), axis=axis)
