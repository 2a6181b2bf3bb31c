"""The speed of sound, solved (issue 27): c as one global parameter of the joint solve, kept only when the data
ask for it.

Odometry gives the sources a metric scale and the arrivals give times, so where both constrain the ranges
(sources spread around the arrays, each array's arrivals over many events) c is determined by the data: a
declared c off by ε scales every range difference d/c by 1 − ε and, with the sources held by the odometry,
moves each array by ~ε × its distance from the sources (1–3 %: 10–21 cm in the rendered rooms).

The parameter is κ = ln(c / c_declared) (``State.cs``; the TDOA factors use c_declared·e^κ, with their
derivatives), with a prior κ ~ N(0, σ²) from the declaration (``Problem.sigma["speed"]``, the option
``speed_of_sound_sigma``). It is tested as the odometry yaw is (estimator/odoframe.py), at the end of the
joint solve with c as declared (outlier rows out, least squares): the same solve with κ free; κ is kept only
when |κ| exceeds SPEED_SIGNIFICANCE of its σ (a likelihood-ratio test of one parameter; a source moving
during the sweep: SPEED_SIGNIFICANCE_MOVING), else c stays as
declared and the solution is exactly the one before this parameter existed. Kept, the joint solve runs again
from the free fit with κ free in every pass (robust, array and outlier tests, least squares, variance
components, the error bars), so each array's σ holds c's uncertainty too.
"""
from __future__ import annotations

import numpy as np

from .problem import make_layout, speed
from .solver import levenberg_marquardt, linearise
from .uncertainty import param_std, whiten
from .variance import vce_factors

# c is solved only where the data tell it from the declared value by this many σ of the free fit (a
# likelihood-ratio test of one parameter, χ² drop ≥ 9: 0.3 % of right-c sessions under honest σ). Below, the data
# cannot tell c apart from the declaration and the declared value is kept (no change at all). With the right c, 40
# rendered sessions (hall, lab, lshape, mixed, moving, office 500-509) gave |z| ≤ 2.9, 6 above 2 (σ ~1.3× short);
# a wrong c of 1 % gave z 2.9-15 in lab and hall (docs/results.md). Not the yaw's 5σ: an undetected c error costs
# 8-40σ in every array, a falsely freed one only c's own scatter (its σ in the error bars).
SPEED_SIGNIFICANCE = 3.0
# A source moving during the sweep (``Problem.motion``: its arrival shifts modelled) holds c to the odometry
# yaw's level: the shifts' model is not exact (the set-up stage's fit, which has none, read c +0.4-2.8 % off on
# moving sessions with the right c), and robot 500 with the right c put it at −0.35 %, 3.7σ (kept at 3σ: 2.1 →
# 3.0 cm); at 5σ a 1 % error is still solved in 6 of 10 moving-source sessions (robot, deploy, moving).
SPEED_SIGNIFICANCE_MOVING = 5.0
MIN_REDUNDANCY = 5.0   # a kind's residuals re-scale the test's σ only with this much redundancy


def speed_test(p, st, lay, kinds, *, max_iter, mask=None, dropped=()):
    """Decide whether c is solved (``p.sigma["speed"]`` > 0, not yet decided: ``p.c_test`` None). From the
    least-squares solution ``st`` with c as declared (outlier rows out: ``mask``; arrays ``dropped`` fixed),
    the same solve with c free; c is kept free when significant (module docstring). Returns (state,
    problem, layout, test record): the free solve's when kept (``p.c_free`` True), else the inputs (``p``
    with ``c_test`` only)."""
    free = free_fit(p, st, lay, kinds, max_iter=max_iter, mask=mask, dropped=dropped)
    if free is None:
        test = {"kept": False}
        return st, p.replace(c_test=test), lay, test
    st_c, p_c, lay_c, test = free
    test["kept"] = bool(np.isfinite(test["std_relative"])
                        and abs(np.log1p(test["relative"])) > test["level"] * test["std_relative"])
    if test["kept"]:
        return st_c, p_c.replace(c_test=test), lay_c, test
    return st, p.replace(c_test=test), lay, test


def free_fit(p, st, lay, kinds, *, max_iter, mask=None, dropped=()):
    """The least-squares solve from ``st`` (c as declared) with κ free, its prior ``p.sigma["speed"]``; None when
    c has no column (no free source). Returns (state, problem, layout, record: declared and fitted c, the
    relative change and its σ under the kinds' a-posteriori sigmas (:func:`kind_scales`), the prior, the level
    of its test)."""
    p_c = p.replace(c_free=True)
    lay_c = make_layout(p_c, arrays=[a for a in range(p.N) if a not in dropped])
    k = int(lay_c.cs[0])
    if k < 0:
        return None
    kinds = list(kinds) + ([] if "speed" in kinds else ["speed"])   # (the prior: active when its σ > 0)
    st_c, _ = levenberg_marquardt(p_c, st, lay_c, kinds, loss=None, mask=mask, max_iter=max_iter)
    lin = linearise(p_c, st_c, lay_c, kinds, mask=mask)
    sd = param_std(whiten(lin.J, lin.w * kind_scales(p_c, st_c, lay_c, kinds, mask, lin) ** -2), k)
    level = SPEED_SIGNIFICANCE if p.motion is None else SPEED_SIGNIFICANCE_MOVING
    return st_c, p_c, lay_c, {"declared_m_s": float(p.c), "fitted_m_s": float(speed(p_c, st_c)),
                              "relative": float(np.expm1(st_c.cs[0])), "std_relative": float(sd),
                              "prior_relative": float(p.sigma["speed"]), "level": level}


def kind_scales(p, st, lay, kinds, mask, lin):
    """(M,): for each residual of ``lin`` its kind's a posteriori σ over the σ used at (``st``, ``lay``, ``mask``)
    — √(Σ r² / Σ (1 − h_ii)), the variance-component step (``variance.vce_factors``; 1 for the priors and kinds
    without redundancy). The test's σ of κ is taken with the sigmas scaled by these: the sigmas were estimated
    (noise="estimate") from the residuals of the solve with c as declared, and a wrong c sets the odometry
    against the far tighter arrivals (hall 500 at −3 %: σ_odo 0.03 m there, 0.0072 with c solved; the test saw
    a 45σ error as 11σ). (The plain RMS, without the redundancy, read the right c of featsim scenes at up to
    3.3σ, RMS 1.6.)"""
    factors = vce_factors(p, st, lay, kinds, mask, MIN_REDUNDANCY)
    return np.concatenate([np.full(len(f.r), np.sqrt(factors.get(f.kind, 1.0))) for f in lin.factors])


def speed_report(p, st, lay, cov, lin):
    """report.json ``speed_of_sound``: the declared and the used c (m/s), the used one's 1-σ (m/s; None when
    not estimated: from the dense covariance ``cov``, or one sparse solve of ``lin``'s Jacobian), whether it
    was estimated and the test that decided it (``p.c_test``; None when untested: ``speed_of_sound="fixed"``)."""
    c, k, sd = speed(p, st), int(getattr(lay, "cs", [-1])[0]), None
    if k >= 0:
        sd = float(np.sqrt(max(cov[k, k], 0.0))) if isinstance(cov, np.ndarray) else \
            param_std(whiten(lin.J, lin.w), k)
    return {"declared_m_s": float(p.c), "value_m_s": float(c), "std_m_s": None if sd is None else float(c * sd),
            "estimated": k >= 0, "test": None if p.c_test is None else dict(p.c_test)}


# speed_of_sound="fixed": the data's c is checked, never used: significant beyond its level in σ (as above) and
# beyond this relative error, the frontend's own bias on the free fit with the right c (0.1-0.5 %: 48 rendered dev
# sessions, hall lab lshape mixed moving office robot 500-509, read |c / c0 − 1| ≤ 0.44 %, none beyond its level).
# Not the set-up stage's 1 % (SOUND_NEAR_TOL): declared 1 % off, hall reads 0.94-0.97 % at 9-15σ with every array
# 35-39σ off (docs/results.md).
CHECK_TOL = 0.005


def speed_check(p, st, lay, kinds, *, prior, max_iter, mask=None, dropped=()):
    """``speed_of_sound="fixed"``: the test of :func:`speed_test` at the final solution ``st`` (c as declared;
    κ's prior σ ``prior``, as "auto" would have it), nothing kept. report.json ``speed_of_sound.check``: the free
    fit's record, its ``z``, ``significant`` (beyond CHECK_TOL and the test's level) and ``shift_m`` — for each
    free non-reference array the move (m, reference frame) that c at the data's value makes: the error the
    declared c leaves in it when the odometry's metre is right (``verdict.name_speed``). None: c has no column."""
    free = free_fit(p.replace(sigma={**p.sigma, "speed": float(prior)}), st, lay, kinds, max_iter=max_iter,
                    mask=mask, dropped=dropped)
    if free is None:
        return None
    st_c, _, lay_c, rec = free
    z = abs(np.log1p(rec["relative"])) / rec["std_relative"] if rec["std_relative"] > 0 else np.nan
    moved = [i for i in range(p.N) if i != p.ref and np.any(lay_c.x[i] >= 0)]
    return {**rec, "z": float(z), "tolerance": CHECK_TOL,
            "significant": bool(np.isfinite(z) and z > rec["level"] and abs(rec["relative"]) > CHECK_TOL),
            "shift_m": {str(p.names[i]): (st_c.x[i] - st.x[i]).tolist() for i in moved}}
