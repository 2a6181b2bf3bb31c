"""An honest verdict on a calibration: ``{"status": "ok" | "suspect" | "failed", "reasons": [...],
"flagged_arrays": [...]}`` (report.json top level; the CLI exits with EXIT_FAILED on "failed").

Every reason is a measured quantity against a documented level (docs/method.md, "Verdict"):

| check | suspect | failed |
| --- | --- | --- |
| solver converged | | not converged (max_iter) |
| RMS normalised residual of a type, against its *stated* sigma (priors) or its estimated sigma (free) | > RESIDUAL_SUSPECT | > RESIDUAL_FAILED, or > RESIDUAL_SUSPECT for TYPES_FAILED types at once |
| fraction of measurements flagged as outliers | > OUTLIER_SUSPECT | > OUTLIER_FAILED or removal cap hit |
| an array inconsistent with the others (dropped, its pose refitted alone) | named | |
| the other arrays/sources move by more than MOVE_SIGMA σ when it is dropped | yes | |
| RMS residual of a type judged against its stated sigma > SIGMA_TOLERANCE, P(χ²) < SIGNIFICANCE | yes | |
"""
from __future__ import annotations

import functools

import numpy as np
from scipy.special import chdtrc, chdtri  # χ² survival function and its inverse: chi2.sf(x, n) = chdtrc(n, x)

from calib.tables import array_param

from .ambiguity import SEPARATION_MIN
from .robust import is_concentrated
from .uncertainty import cover_alternative

RESIDUAL_SUSPECT = 3.0   # RMS residual 3× its sigma: the weights (or the model) are wrong
RESIDUAL_FAILED = 10.0   # 10×: the data contradict the model (e.g. wrong emission times)
OUTLIER_SUSPECT = 0.15   # fraction of measurements removed as outliers
OUTLIER_FAILED = 0.30
TYPES_FAILED = 2         # residuals of this many types above RESIDUAL_SUSPECT at once: the model is wrong
MOVE_SIGMA = 3.0         # a dropped array moved the rest by more than this many σ
PRIOR_BOUND = 10.0       # a type whose sigma may grow less than this is judged against its stated sigma
SIGMA_TOLERANCE = 1.5    # a stated sigma may be off by this factor (the frontend's honest-sigma bound) ...
SIGNIFICANCE = 1e-3      # ... an excess beyond it this improbable under the stated sigma is reported
STATUS_RANK = {"ok": 0, "suspect": 1, "failed": 2}
TYPE_LABEL = {"tdoa_s": "TDOA-S", "tdoa_m": "TDOA-M", "doa": "DOA", "odometry": "odometry", "cone": "cone (pair axis)"}


def residual_ratios(variance_factors, scales, bounds):
    """RMS normalised residual per type against the sigma that counts.

    variance_factors : {kind: Σ r² / redundancy at the solution, with the sigmas used}.
    scales : {kind: sigma used / sigma stated} (variance components; 1 when not estimated).
    bounds : {kind: the largest factor allowed}; a type whose bound is the prior's (small) is judged
        against its stated sigma, a free type against its estimated sigma (so a bound hit still shows).
    """
    out = {}
    for kind, vf in variance_factors.items():
        r = float(np.sqrt(max(vf, 0.0)))
        s = float(scales.get(kind, 1.0))
        b = float(bounds.get(kind, np.inf))
        prior = b < PRIOR_BOUND
        out[kind] = r * s if prior else r * (s if s >= b * (1 - 1e-9) else 1.0)
    return out


def stated_sigma_excess(ratios, counts, bounds):
    """Types judged against their stated sigma (bound < PRIOR_BOUND, e.g. odometry) whose RMS residual
    exceeds it by more than SIGMA_TOLERANCE with ``P(χ²(n) > n·ratio²) < SIGNIFICANCE`` (n residual values:
    more than the redundancy, so the test is conservative). Such an excess is what biased measurements of
    another type leave when the solution absorbs them (arrivals biased with the geometry move the sources;
    the odometry then disagrees): {kind: (ratio, n)}."""
    out = {}
    for kind, r in ratios.items():
        n = int(counts.get(kind, 0))
        if n < 1 or float(bounds.get(kind, np.inf)) >= PRIOR_BOUND:
            continue
        if r > SIGMA_TOLERANCE and chdtrc(n, n * r * r) < SIGNIFICANCE:
            out[kind] = (float(r), n)
    return out


def concentrated_outliers(outliers, rows_per_array):
    """Arrays holding most of the outlier rows: {array: (its outliers, its rows)} (``robust.is_concentrated``)."""
    total = len(outliers)
    out = {}
    for a, n_rows in rows_per_array.items():
        k = sum(1 for o in outliers if o.get("array") == a)
        if is_concentrated(k, total, n_rows):
            out[a] = (k, n_rows)
    return out


def make_verdict(*, converged, reason, ratios, n_outliers, n_measurements, capped, arrays, odometry_yaw=None,
                 concentrated=None, excess=None):
    """The verdict dict from the estimator's diagnostics.

    ratios : {kind: RMS normalised residual} (:func:`residual_ratios`); arrays: the consistency records
    of ``joint.consistency_stage`` (``array``, ``inconsistent``, ``moves_sigma``); odometry_yaw: the
    yaw test ({yaw_deg, std_deg, kept}) — a kept yaw means the odometry is not in the frame it was said to be.
    excess: :func:`stated_sigma_excess`.
    """
    status, reasons = "ok", []

    def worse(s, text):
        nonlocal status
        reasons.append(text)
        if STATUS_RANK[s] > STATUS_RANK[status]:
            status = s

    if not converged:
        worse("failed", f"not converged ({reason})")
    high = [k for k, r in ratios.items() if r > RESIDUAL_SUSPECT]
    for kind, r in ratios.items():
        label = TYPE_LABEL.get(kind, kind)
        if r > RESIDUAL_FAILED or (r > RESIDUAL_SUSPECT and len(high) >= TYPES_FAILED):
            why = f"> {RESIDUAL_FAILED:g}" if r > RESIDUAL_FAILED else \
                f"> {RESIDUAL_SUSPECT:g} for {len(high)} measurement types at once"
            worse("failed", f"{label} residuals {r:.1f}× their sigma ({why}: the data contradict the model)")
        elif r > RESIDUAL_SUSPECT:
            worse("suspect", f"{label} residuals {r:.1f}× their sigma (> {RESIDUAL_SUSPECT:g})")
        elif kind in (excess or {}):
            n = excess[kind][1]
            worse("suspect", f"{label} residuals {r:.2f}× their stated sigma over {n} values (> {SIGMA_TOLERANCE:g}, "
                             f"P < {SIGNIFICANCE:g} under it): other measurements pull the solution away from it "
                             "(e.g. arrival times biased with the geometry, absorbed by the source positions)")
    frac = n_outliers / max(n_measurements, 1)
    if capped or frac > OUTLIER_FAILED:
        worse("failed", f"{n_outliers} of {n_measurements} measurements ({100 * frac:.0f} %) are outliers "
                        f"(> {100 * OUTLIER_FAILED:.0f} %{' or removal stopped at its cap' if capped else ''})")
    elif frac > OUTLIER_SUSPECT:
        worse("suspect", f"{n_outliers} of {n_measurements} measurements ({100 * frac:.0f} %) are outliers "
                         f"(> {100 * OUTLIER_SUSPECT:.0f} %)")
    flagged = []
    for a in arrays:
        if not a.get("inconsistent"):
            continue
        flagged.append(a["array"])
        worse("suspect", f"array {a['array']} is inconsistent with the others (χ² drop {a['drop_chi2']:.0f} on "
                         f"{a['drop_dof']} dof): solved without it, its own pose refitted alone is unreliable")
        if a.get("moves_sigma", 0.0) > MOVE_SIGMA:
            worse("suspect", f"dropping array {a['array']} moves the solution by {a['moves_sigma']:.1f} σ "
                             f"(> {MOVE_SIGMA:g})")
    for a, (k, n_rows) in (concentrated or {}).items():
        if a not in flagged:
            flagged.append(a)
            worse("suspect", f"array {a} holds {k} of the {n_outliers} outliers ({k} of its {n_rows} rows): its "
                             "data may be biased as a whole (reflections, occlusion)")
    if odometry_yaw and odometry_yaw.get("kept"):
        worse("suspect", f"the odometry frame is rotated by {odometry_yaw['yaw_deg']:.1f} ± {odometry_yaw['std_deg']:.1f}° "
                         "about the vertical relative to the reference array (estimated; check the odometry's axes, and "
                         "the arrays' mic geometry and doa_hemisphere: a mirrored or mis-ordered geometry turns the "
                         "DOAs the same way)")
    return {"status": status, "reasons": reasons, "flagged_arrays": flagged}


def flag(verdict, *arrays):
    """Add ``arrays`` to ``verdict["flagged_arrays"]`` (in place), each once, in order."""
    for a in arrays:
        if a not in verdict["flagged_arrays"]:
            verdict["flagged_arrays"].append(a)


def name_inconsistent(verdict, record):
    """Name the arrays the leave-one-array-out test found inconsistent (``estimator.consistency``; ``record``:
    report.json ``leave_one_out``), in place: flagged, status at least ``suspect``, the reason with the largest
    move each caused and what was done: solved without it (``isolated``: the rest then tested consistent), or
    kept (its pull within the noise that leaving it out adds, or no single array explains the inconsistency:
    then every array tested is flagged). An array the trial without it gave back (``readmitted``: clock terms,
    found once its rows were out, explain them; the whole then tests consistent) is not flagged: the reason says
    what its rows did before those terms."""
    found = record["inconsistent"]
    for t in found:
        if t.get("readmitted"):
            verdict["reasons"].append(
                f"array {t['array']} was inconsistent with the others until its clock terms were modelled: leaving "
                f"it out moved {t['moved']} by {100 * t['move_m']:.1f} cm (Hausman T = {t['T']:.1f} on {t['dof']} "
                f"dof, p = {t['p']:.1g} < {t['alpha']:.1g}); without its rows its clock's terms showed (report.json "
                "clock), and with them its rows agree with the others'")
            continue
        if t["isolated"]:
            then = "solved without its rows (the others then agree); its own pose, refitted alone, is unreliable"
        elif not t["helps"]:
            then = (f"kept: its pull on the others is within the noise that leaving it out would add "
                    f"({100 * t['noise_m']:.1f} cm)")
        else:
            then = "kept: leaving it out does not make the others agree"
        verdict["reasons"].append(
            f"array {t['array']} is inconsistent with the others: leaving it out moves {t['moved']} by "
            f"{100 * t['move_m']:.1f} cm (Hausman T = {t['T']:.1f} on {t['dof']} dof, p = {t['p']:.1g} < "
            f"{t['alpha']:.1g}): rows biased with the geometry (e.g. a clock or mic-geometry error the residuals "
            f"do not show); {then}")
        flag(verdict, t["array"])
        verdict["status"] = max(verdict["status"], "suspect", key=STATUS_RANK.get)
    if not record.get("explained", True):
        verdict["reasons"].append(f"the arrays' positions depend on {', '.join(t['array'] for t in found)} beyond "
                                  "their noise and leaving out no single one of them makes the rest agree: the "
                                  "positions of every array tested are in doubt")
        flag(verdict, *(t["array"] for t in record["rounds"][0]["tested"]))
    return verdict


REASON_TEXT = {"nlos": "reflection-only arrivals (late against the array's range track, or no direct path in "
                       "their waveform: line of sight blocked)",
               "weak_direct": "direct paths weaker than a reflection just after them (line of sight attenuated: "
                              "occlusion by a mount or obstacle), whose DOAs that reflection bends",
               "absurd": "TDOAs no room can produce (> 100 m of path off the array's clock line)"}


def name_distrusted(verdict, screened):
    """Name the arrays and events the estimator did not trust (``estimator.screen``), in place.

    ``verdict["distrusted"]`` (only when there is any): one {array, reason, events} per array and reason, for the rows taken out
    (their arrays were calibrated from the rest) and for arrays most of whose rows are in doubt (kept:
    there is too little else; the array is then flagged and the status at least ``suspect``). Absurd rows
    make the status ``suspect`` too: something upstream failed."""
    # the events whose arrival AT the array is in doubt: its DOA rows' when it has any (a TDOA-S row names
    # two events, a TDOA-M row carries the reference's doubts too), else its TDOA-M rows', else TDOA-S
    rank = {"doa": 0, "tdoa_m": 1, "tdoa_s": 2}
    best = {}
    for r in screened["rows"]:
        if r.get("via_reference"):
            continue   # a TDOA-M row out for the reference's arrival: named under the reference
        key = (r["array"], r["reason"])
        k = rank.get(r["type"], 2)
        if key not in best or k < best[key][0]:
            best[key] = (k, set())
        if k == best[key][0]:
            best[key][1].update(r["events"])
    groups = {key: ev for key, (_, ev) in best.items()}
    listed = [{"array": a, "reason": why, "events": sorted(ev), "taken_out": True}
              for (a, why), ev in sorted(groups.items())]
    worst = verdict["status"]
    for a, n in sorted(screened["kept_doubted"].items()):
        whys = screened.get("kept_reasons", {}).get(a, ["nlos"])
        listed += [{"array": a, "reason": why, "events": [], "taken_out": False} for why in whys]
        flag(verdict, a)
        verdict["reasons"].append(f"array {a}: in {n} of its events its arrivals are "
                                  f"{' / '.join(REASON_TEXT[w] for w in whys)}: most of its data, kept; "
                                  "its calibration is not trusted")
        worst = max(worst, "suspect", key=STATUS_RANK.get)
    for a, counts in sorted(screened.get("mostly_taken_out", {}).items()):
        for why, (n, m) in counts.items():
            flag(verdict, a)
            verdict["reasons"].append(f"array {a}: in {n} of its {m} events its arrivals are {REASON_TEXT[why]}: "
                                      f"taken out, calibrated from its other {m - n} events (its std says how well)")
            worst = max(worst, "suspect", key=STATUS_RANK.get)
    absurd = sorted({a for (a, why) in groups if why == "absurd"})
    if absurd:
        verdict["reasons"].append(f"{sum(len(groups[(a, 'absurd')]) for a in absurd)} event(s) of array(s) "
                                  f"{', '.join(absurd)} had {REASON_TEXT['absurd']}: taken out")
        worst = max(worst, "suspect", key=STATUS_RANK.get)
    nlos = [a for (a, why) in groups if why == "nlos"]
    if nlos:
        verdict["reasons"].append("not trusted, taken out: " + "; ".join(
            f"{a} events {', '.join(map(str, sorted(groups[(a, 'nlos')])))}" for a in nlos)
            + f" ({REASON_TEXT['nlos']})")
    verdict["status"] = worst
    if listed:
        verdict["distrusted"] = listed
    return verdict


def fold_ambiguity(out, basins):
    """Arrays whose other fold basin (``init.fold_basins``) fits as well (``ambiguous``; the lower-cost one is
    reported, switched or not): their covariance widened to cover the other basin
    (``uncertainty.cover_alternative``), and the verdict names them (``suspect``). In place on ``calibrate``'s
    output."""
    verdict = out["report"]["verdict"]
    for b in basins:
        if not b["ambiguous"]:
            continue
        cover_alternative(out, b["array"], b["displacement_m"], b["rotvec"])
        flag(verdict, b["array"])
        verdict["reasons"].append(f"array {b['array']}: its sources all lie near its mic plane, where planar DOAs "
                                  f"fold; another orientation {b['rotation_deg']:.0f}° away fits as well (cost "
                                  f"{-b['dcost'] if b['switched'] else b['dcost']:+.1f}): its std covers both")
        verdict["status"] = max(verdict["status"], "suspect", key=STATUS_RANK.get)
    return out

def mirror_ambiguity(out, records):
    """Arrays with a mirror solution across their sources' plane that the data do not exclude
    (``estimator.ambiguity.mirror_basins``, ``ambiguous``; the lower-cost one is reported): named in the
    verdict (``suspect``) with how far the other solution lies and what would break the tie, and their
    covariance widened to cover it (``uncertainty.cover_alternative``). In place on ``calibrate``'s output."""
    verdict = out["report"]["verdict"]
    for r in records:
        if not r["ambiguous"]:
            continue
        cover_alternative(out, r["array"], r["displacement_m"], r["rotvec"])
        fix = {"planar": "state its doa_hemisphere or drive a path whose height varies",
               "linear": "drive a path whose height varies (a linear board's DOAs cannot tell the sides apart)",
               }.get(r.get("board"), "drive a path whose height varies")
        flag(verdict, r["array"])
        verdict["reasons"].append(
            f"array {r['array']}: its pose has a mirror solution across the sources' plane {r['position_m']:.2f} m "
            f"away that fits as well (cost {-r['dcost'] if r['switched'] else r['dcost']:+.1f}; the two are "
            f"{r['separation_chi2']:.0f} apart in χ², a choice needs {SEPARATION_MIN:g}: its sources lie "
            f"{100 * r['plane']['source_spread_m']:.0f} cm from that plane, RMS): its std covers both; {fix}")
        verdict["status"] = max(verdict["status"], "suspect", key=STATUS_RANK.get)
    return out


SETUP_PREFIX = "set-up: "
# generic reasons that a set-up mistake produces as a symptom; named as such when set-up findings failed
SYMPTOM_NOTE = " (probably a symptom of the set-up finding(s) above, not a cause of its own)"


def with_setup(verdict, findings):
    """The verdict with the set-up findings (``calib.pipeline.setupcheck``: dicts with status "failed",
    "suspect" or "note", text, array or arrays) ranked above the estimator's own reasons: a mistake in the set-up is
    the cause, the residuals and the odometry's apparent rotation its symptoms. A failed finding makes the
    verdict failed (the result cannot be trusted, whatever the residuals say); a suspect one at least
    suspect. The arrays named are added to ``flagged_arrays``. Returns a new dict."""
    status = verdict.get("status", "ok")
    setup, flagged = [], list(verdict.get("flagged_arrays", []))
    for f in findings:
        if f.get("status") not in STATUS_RANK:
            continue
        setup.append(SETUP_PREFIX + f["text"])
        if STATUS_RANK[f["status"]] > STATUS_RANK[status]:
            status = f["status"]
        for a in [f["array"]] if f.get("array") else list(f.get("arrays") or ()):
            if a not in flagged:
                flagged.append(a)
    failed = any(f.get("status") == "failed" for f in findings)
    generic = [r + SYMPTOM_NOTE if failed else r for r in verdict.get("reasons", [])]
    return {**verdict, "status": status, "reasons": setup + generic, "flagged_arrays": flagged}


def majority_apart(verdict, unreliable, n_arrays, reference=None):
    """``failed`` when more than half of the non-reference arrays were solved apart (refitted alone, std NaN:
    their rows distrusted as a whole or inconsistent with the others): no consistent majority holds the frame,
    and the arrays left in it are as likely the odd ones out (ushape seed 62 before issue 27's screening: three
    of four arrays refitted alone from reflections, 4.7-7.5 m off, the fourth 8 cm, verdict `suspect`).
    Likewise when the ``reference`` array itself was solved apart: every pose is reported in its frame, which
    then only the odometry ties to the others (lshape seed 390: the reference's DOAs 250× their σ, dropped, the
    others placed through the odometry with its yaw free, 175° round and 7-11 m off, verdict `suspect`). In place."""
    apart = list(unreliable)
    others = [a for a in apart if a != reference]
    if n_arrays > 1 and len(others) > (n_arrays - 1) / 2:
        verdict["reasons"].append(f"{len(others)} of the {n_arrays - 1} non-reference arrays ({', '.join(others)}) "
                                  "were solved apart from the others: no consistent majority holds the calibration")
        verdict["status"] = "failed"
        flag(verdict, *others)
    if reference is not None and reference in apart:
        verdict["reasons"].append(f"the reference array {reference} was solved apart from the others: every pose is "
                                  "given in its frame, which its own rows no longer tie to the rest")
        verdict["status"] = "failed"
        flag(verdict, reference)
    return verdict


def median_norm_factor(d):
    """Median of |e| / sqrt(E|e|²) for e ~ N(0, σ² I_d): the typical error of a d-axis estimate over its
    RMS std (the ``*_std`` columns' norm); 0.888 for a position (d = 3), 0.833 for an axis direction (d = 2)."""
    return float(np.sqrt(chdtri(d, 0.5) / d))


NORM_DRAWS = 16384  # standard normal draws (fixed seed) for the median error of unequal per-axis stds


@functools.cache
def _unit_draws(d):
    return np.random.default_rng(20261128).standard_normal((NORM_DRAWS, d))


def _finite(stds):
    s = np.asarray(stds, dtype=float)
    return s[np.isfinite(s)]


def median_error(stds):
    """Median of |e| for e ~ N(0, diag(stds²)) (the finite ``stds`` of one array's axes; 0 when none): a
    position or orientation's typical error from its per-axis std. Exact for equal stds
    (``median_norm_factor``); with one dominant axis it tends to that axis' half-normal median (0.674 σ)."""
    s = _finite(stds)
    if not len(s):
        return 0.0
    if np.ptp(s) <= 1e-9 * s.max():
        return median_norm_factor(len(s)) * float(np.sqrt(np.sum(s ** 2)))
    return float(np.median(np.linalg.norm(_unit_draws(len(s)) * s, axis=1)))


def exceed_probability(stds, target):
    """P(|e| > target) for e ~ N(0, diag(stds²)) (the finite ``stds``; 0 when none or target ≤ 0): exact for
    equal stds (|e|² / σ² ~ χ²_d), else over the NORM_DRAWS fixed-seed draws of ``median_error``."""
    s = _finite(stds)
    if not len(s) or target <= 0 or s.max() <= 0:
        return 0.0
    if np.ptp(s) <= 1e-9 * s.max():
        return float(chdtrc(len(s), (target / s[0]) ** 2))
    return float(np.mean(np.linalg.norm(_unit_draws(len(s)) * s, axis=1) > target))


def _norm(stds):
    """The norm of the finite per-axis stds (the summary's ±pos / ±rot)."""
    return float(np.sqrt(np.sum(_finite(stds) ** 2)))


# An `ok` vouches for every array within the precision target. An array is named when its stated covariance
# gives its error more than this chance of lying beyond the target, so that no more than this share of the
# arrays left unnamed is expected beyond it (with honest stds; docs/method.md "Precision target"). It was 0.5
# (name when the error is more likely above than below: a quarter to a half of the unnamed arrays near the
# target were beyond it, as their stds said).
EXCEED_ALPHA = 0.2


def name_imprecise(verdict, arrays, target_position, target_orientation_deg, alpha=EXCEED_ALPHA):
    """Name the arrays whose stated std gives their error more than ``alpha`` chance of exceeding the target:
    ``exceed_probability`` of the per-axis stds, position (m) or orientation (deg; the axes the board
    determines: two for a linear board or a pair). The data do not determine those arrays to the precision asked
    for, whatever the rest of the verdict says (e.g. a board with few chirps near it, or with its direct path in
    few of them). 0 turns a target off; the reference array and arrays already named are left alone. In place;
    returns report.json's ``precision`` record (``alpha``; per named array its stds and probabilities)."""
    record = {"target_position_m": float(target_position), "target_orientation_deg": float(target_orientation_deg),
              "alpha": float(alpha), "arrays": []}
    for _, row in arrays.iterrows():
        name = str(row["array"])
        if name in verdict["flagged_arrays"]:
            continue
        pos_s = [row[c] for c in array_param("x").std_columns]
        rot_s = np.degrees([row[c] for c in array_param("rot").std_columns])
        p_pos = exceed_probability(pos_s, target_position)
        p_rot = exceed_probability(rot_s, target_orientation_deg)
        short = [f"{what} ±{v:.1f}{unit} (P = {p:.2f})" for what, v, unit, p in
                 (("position", 100 * _norm(pos_s), " cm", p_pos), ("orientation", _norm(rot_s), "°", p_rot))
                 if p > alpha]
        if not short:
            continue
        record["arrays"].append({"array": name, "position_std_m": _norm(pos_s), "orientation_std_deg": _norm(rot_s),
                                 "p_beyond_position": p_pos, "p_beyond_orientation": p_rot})
        flag(verdict, name)
        verdict["reasons"].append(
            f"array {name} is not determined to the target {100 * target_position:g} cm / {target_orientation_deg:g}° "
            f"({' and '.join(short)}, 1σ; P: the chance its error is beyond the target, > {alpha:g}): more chirps "
            "near it or with its direct path would narrow it (targets: --target-position, --target-orientation)")
        verdict["status"] = max(verdict["status"], "suspect", key=STATUS_RANK.get)
    return record


SPEED_SHIFT_SIGMA = 1.0   # an array that the data's c moves by more than this many of its σ (one axis) is named


def name_speed(verdict, check, arrays):
    """Name the arrays a declared speed of sound off the data's leaves wrong (``speed_of_sound="fixed"``; ``check``:
    ``soundspeed.speed_check``'s record or None; ``arrays``: arrays.csv's frame, its stated std), in place: when
    the data ask for another c (``significant``), each non-reference array that c would move beyond
    SPEED_SHIFT_SIGMA of its std on some axis is flagged, status at least ``suspect``. The data fix c only against
    the odometry's metre, so the reason offers both readings. ``check`` gets ``named`` (those arrays), ``added``
    (those no other reason had flagged) and ``status_before``, so that a finding blaming the odometry's scale can
    give them back (``pipeline.setupcheck.settled_by_estimate``). Returns the arrays named."""
    if not check or not check.get("significant"):
        return []
    std = arrays.set_index("array")[list(array_param("x").std_columns)].astype(float)
    moved = {a: float(np.max(np.abs(d) / std.loc[a].to_numpy())) for a, d in check["shift_m"].items()
             if a in std.index and np.all(std.loc[a].to_numpy() > 0)}
    named = [a for a, z in moved.items() if z > SPEED_SHIFT_SIGMA]
    if not named:
        return []
    c0, c, rel = check["declared_m_s"], check["fitted_m_s"], check["relative"]
    shift = max(float(np.linalg.norm(check["shift_m"][a])) for a in named)
    check.update(named=named, added=[a for a in named if a not in verdict["flagged_arrays"]],
                 status_before=verdict["status"])
    flag(verdict, *named)
    verdict["reasons"].append(
        f"the speed of sound: the arrivals against the metric odometry ask for {c:.1f} ± {c0 * check['std_relative']:.1f} "
        f"m/s, {100 * rel:+.1f} % ({check['z']:.1f}σ) from the declared {c0:g} m/s, which places every array "
        f"in the arrivals' metre: with the data's c {', '.join(named)} move by up to {100 * shift:.1f} cm (up to "
        f"{max(moved[a] for a in named):.1f}× their std). Check the air's temperature (331.3 + 0.606·T °C) and "
        "declare its c, or solve it (`--speed-of-sound auto`) — or, if the declared c is right, the odometry's "
        f"distances are {abs(100 * rel):.1f} % too {'long' if rel > 0 else 'short'} (wheel diameter, encoder "
        "scale): then the arrays are right as they are")
    verdict["status"] = max(verdict["status"], "suspect", key=STATUS_RANK.get)
    return named
