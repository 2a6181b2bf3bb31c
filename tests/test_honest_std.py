"""Honest error bars (issue 27): the covariance the ``*_std`` columns report (``uncertainty.honest_covariance``)
against independent truth — arrival errors drawn by hand, arrays made noisier or correlated on purpose,
and a Monte-Carlo of scenes whose TDOA rows share their arrivals as a frontend's do."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.errors import InputError
from calib.estimator import calibrate
from calib.estimator.factors import active_kinds
from calib.estimator.problem import make_layout
from calib.estimator.solver import linearise
from calib.estimator import uncertainty as U
from calib.estimator.uncertainty import arrival_rows, covariance
from calib.estimator.variance import covariance_factors
from calib.pipeline.formats.io import validate_meta
from calib.pipeline.simulate.featsim import simulate_features

SIGMA = 1e-4   # the paper's TDOA sigma (s)


def _shared_arrivals(seed, sigma=SIGMA):
    """A paper scene (trajectory 3) whose TDOAs are differences of one noisy arrival per (array, event)
    (std sigma/√2, so each row's std is the stated sigma), DOAs and odometry with the simulator's noise;
    meta.json says so. Returns (features, truth)."""
    feats, truth = simulate_features(3, sigma_tdoa=sigma, seed=seed)
    exact, _ = simulate_features(3, sigma_tdoa=sigma, seed=seed, noise=False)   # same scene, exact values
    rng = np.random.default_rng(1000 + seed)
    ref, K = exact["meta"]["reference_array"], len(exact["events"])
    n = {a: rng.normal(0.0, sigma / np.sqrt(2), K) for a in exact["meta"]["arrays"]}
    tm, ts = exact["tdoa_m"].copy(), exact["tdoa_s"].copy()
    tm["tdoa"] += [n[a][e] - n[ref][e] for a, e in zip(tm["array"], tm["event"])]
    ts["tdoa"] += [n[a][b] - n[a][e] for a, e, b in zip(ts["array"], ts["from_event"], ts["to_event"])]
    return feats.replace(tdoa_m=tm, tdoa_s=ts, meta={**feats["meta"], "tdoa_shared_arrivals": True}), truth


def _final_linearisation(cal):
    p, st = cal["problem"], cal["state"]
    lay = make_layout(p)
    lin = linearise(p, st, lay, active_kinds(p))
    return p, lay, lin


def test_arrival_rows_are_the_rows_differences_of_arrivals():
    """D maps arrival errors (in units of their sigma) to the whitened TDOA row errors: checked against
    the rows' definitions (TDOA-M a_ij − a_ref,j, TDOA-S a_ib − a_ia) written out by hand."""
    feats, _ = _shared_arrivals(0)
    p, lay, lin = _final_linearisation(calibrate(feats))
    D = arrival_rows(p, lin, {}).toarray()
    rng = np.random.default_rng(3)
    sig_a = p.sigma["tdoa_s"] / np.sqrt(2)
    e = rng.normal(0.0, sig_a, (p.N, p.K))   # arrival errors (s)
    expect, start = np.zeros(len(lin.r)), 0
    for f in lin.factors:
        n = len(f.r)
        if f.kind == "tdoa_m":
            rows = p.tdoa_m
            expect[start:start + n] = (e[rows.arr, rows.ev] - e[p.ref, rows.ev]) / p.sigma["tdoa_m"]
        elif f.kind == "tdoa_s":
            rows = p.tdoa_s
            expect[start:start + n] = (e[rows.arr, rows.b] - e[rows.arr, rows.a]) / p.sigma["tdoa_s"]
        start += n
    assert D @ (e / sig_a).ravel() == pytest.approx(expect, abs=1e-12)
    # rows of other kinds hold no arrival; every TDOA row's error has unit variance
    C = D @ D.T
    tdoa = np.abs(D).sum(axis=1) > 0
    assert np.diag(C)[tdoa] == pytest.approx(1.0)
    assert np.count_nonzero(tdoa) == len(p.tdoa_m) + len(p.tdoa_s)


def _rotate_doas(feats, array, rotvecs):
    """doa.csv with the rows of ``array`` (in event order) rotated by ``rotvecs`` (m, 3) rad."""
    doa = feats["doa"].copy()
    m = (doa["array"] == array).to_numpy()
    order = np.argsort(doa.loc[m, "event"].to_numpy(), kind="stable")
    u = doa.loc[m, ["ux", "uy", "uz"]].to_numpy()[order]
    u = Rotation.from_rotvec(rotvecs).apply(u)
    vals = np.empty_like(u)
    vals[order] = u
    doa.loc[m, ["ux", "uy", "uz"]] = vals
    return feats.replace(doa=doa)


def _doa_factors(feats):
    p, lay, lin = _final_linearisation(calibrate(feats, noise="meta"))
    return dict(zip(p.names, covariance_factors(p, lin, covariance(lin.J[lin.w > 0], lay.n, lay))["doa"]))


def test_a_noisier_array_gets_its_own_factor():
    """One array's DOAs 3× noisier than the rest (and than stated): its rows' σ² factor is near 9, the
    others' stay near 1 (the covariance, not the solve, is inflated)."""
    feats, _ = simulate_features(3, sigma_tdoa=SIGMA, sigma_doa_deg=2.0, seed=4)
    sd = np.radians(feats["meta"]["sigma_doa_deg"])   # per tangent axis
    K = len(feats["events"])
    noisy = _rotate_doas(feats, "A3", np.random.default_rng(5).normal(0.0, 2 * np.sqrt(2) * sd, (K, 3)))
    f = _doa_factors(noisy)
    assert 4.0 < f["A3"] < 20.0
    assert all(v < 2.0 for a, v in f.items() if a != "A3")
    clean = _doa_factors(feats)
    assert max(clean.values()) < 2.0


def test_errors_that_drift_along_the_trajectory_inflate():
    """An array whose DOA errors follow a slow random walk (each event's close to the last: correlated,
    as a reflection or the robot's motion makes them) gets a factor above 1 from the lag-1 correlation,
    while the same errors shuffled in time (independent, same size) do not reach it."""
    feats, _ = simulate_features(3, sigma_tdoa=SIGMA, sigma_doa_deg=2.0, seed=6)
    sd = np.radians(feats["meta"]["sigma_doa_deg"])
    K = len(feats["events"])
    rng = np.random.default_rng(7)
    walk = np.cumsum(rng.normal(0.0, sd, (K, 3)), axis=0)
    walk -= walk.mean(axis=0)   # (a constant rotation is the array's orientation: no information)
    walk *= 2 * sd / np.sqrt(np.mean(walk ** 2))
    drifting = _doa_factors(_rotate_doas(feats, "A2", walk))["A2"]
    shuffled = _doa_factors(_rotate_doas(feats, "A2", walk[rng.permutation(K)]))["A2"]
    assert drifting > 1.5 * shuffled


@pytest.mark.slow
def test_shared_arrivals_error_bars_are_honest():
    """Over 24 scenes whose TDOA rows share arrivals, position and clock-offset errors / stated std have an
    RMS near 1 (a Gaussian's), and no worse than the std that treats the rows as independent."""
    z = {True: [], False: []}
    for seed in range(24):
        feats, truth = _shared_arrivals(seed)
        t = truth["arrays"].set_index("array")
        for shared in (True, False):
            f = feats if shared else feats.replace(meta={**feats["meta"], "tdoa_shared_arrivals": False})
            a = calibrate(f)["arrays"].set_index("array")
            keep = [n for n in a.index if np.isfinite(a.loc[n, "x_std"])]
            for col in ("x", "y", "z", "offset"):
                z[shared] += list((a.loc[keep, col] - t.loc[keep, col]) / a.loc[keep, f"{col}_std"])
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    assert 0.8 < rms[True] < 1.15
    assert abs(rms[True] - 1.0) <= abs(rms[False] - 1.0) + 0.02


def test_meta_key_is_a_boolean():
    base = {"speed_of_sound": 343.0, "reference_array": "A1", "arrays": ["A1", "A2"]}
    assert validate_meta({**base, "tdoa_shared_arrivals": True})["tdoa_shared_arrivals"] is True
    with pytest.raises(InputError, match="tdoa_shared_arrivals"):
        validate_meta({**base, "tdoa_shared_arrivals": 1})


def _planar_near_plane(seed, sigma_p_deg=0.3):
    """A scene (16 stops 6 × 5 m, heights 1.0–1.4 m, arrays among them) in which array A2 is a planar 6-mic circle whose mic plane is the plane closest to all
    its sources (its true directions' least-squares plane) and whose DOAs err as a planar array's do: an
    in-plane error of std σ_p per axis, the elevation then recovered from the in-plane length (clipped
    at the plane). Returns (features, truth)."""
    rng = np.random.default_rng(50 + seed)
    stops = np.column_stack([rng.uniform(0, 6, 16), rng.uniform(0, 5, 16), rng.uniform(1.0, 1.4, 16)])
    feats, truth = simulate_features(stops, sigma_tdoa=SIGMA, sigma_doa_deg=1.0, seed=seed)
    t = truth["arrays"].set_index("array")
    R = Rotation.from_quat(t.loc["A2", ["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
    src = truth["sources"].set_index("event").loc[:, ["x", "y", "z"]]
    doa = feats["doa"].copy()
    m = (doa["array"] == "A2").to_numpy()
    w = src.loc[doa.loc[m, "event"]].to_numpy(float) - t.loc["A2", ["x", "y", "z"]].to_numpy(float)
    u = R.inv().apply(w / np.linalg.norm(w, axis=1, keepdims=True))
    normal = np.linalg.svd(u - u.mean(axis=0))[2][2]
    normal *= np.sign(np.mean(u @ normal)) or 1.0
    side = np.sign(u @ normal)
    v = u - (u @ normal)[:, None] * normal
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    v += rng.normal(0.0, np.radians(sigma_p_deg), (len(v), 2)) @ np.array([e1, e2])
    rho = np.minimum(np.linalg.norm(v, axis=1), 1.0)
    meas = v / np.linalg.norm(v, axis=1, keepdims=True) * rho[:, None] + (side * np.sqrt(1 - rho ** 2))[:, None] * normal
    doa.loc[m, ["ux", "uy", "uz"]] = meas
    ring = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]) * 0.04
    mics = {str(a): [[0.0, 0.0, 0.0]] for a in feats["meta"]["arrays"]}
    mics["A2"] = (ring @ np.array([e1, e2])).tolist()
    return feats.replace(doa=doa, meta={**feats["meta"], "mics": mics}), truth, float(np.max(np.abs(u @ normal)))


def test_planar_array_near_its_plane_is_honest_in_tilt():
    """A planar array whose sources lie near its mic plane measures azimuth well and elevation badly: over
    8 scenes its orientation error / stated std stays Gaussian-sized with the planar model (meta ``mics``),
    where the isotropic row sigma claims too much."""
    z = {True: [], False: []}
    for seed in range(8):
        feats, truth, _ = _planar_near_plane(seed)
        t = truth["arrays"].set_index("array")
        qt = Rotation.from_quat(t.loc["A2", ["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
        for planar in (True, False):
            f = feats if planar else feats.replace(meta={k: v for k, v in feats["meta"].items() if k != "mics"})
            a = calibrate(f, noise="meta")["arrays"].set_index("array")
            qe = Rotation.from_quat(a.loc["A2", ["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
            z[planar].append((qe * qt.inv()).magnitude() / np.linalg.norm(a.loc["A2", ["rx_std", "ry_std", "rz_std"]]))
    z = {k: np.array(v)[np.isfinite(z[True]) & np.isfinite(z[False])] for k, v in z.items()}  # (a degenerate draw)
    assert len(z[True]) >= 6
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    assert max(z[True]) < 2.5 and rms[True] < 1.3
    assert rms[False] > 1.5 * rms[True]


def _planar_rows_of_unequal_sigma(seed, sig_deg=0.3, wild=20.0, share=0.2):
    """A paper scene (trajectory 3) of planar 6-mic circles (meta ``mics``) whose DOA rows have unequal sigmas, as
    a frontend's do where a reflection spreads some chirps' plane-wave fits (lshape 500's A4: rows of 0.12° beside
    rows of 14°): a ``share`` of the rows at ``wild`` × ``sig_deg``, each row's error drawn at its own sigma
    (doa.csv ``sigma_deg``, per tangent axis). Returns (features, truth)."""
    exact, truth = simulate_features(3, sigma_tdoa=SIGMA, seed=seed, noise=False)
    feats, _ = simulate_features(3, sigma_tdoa=SIGMA, seed=seed)
    rng = np.random.default_rng(4000 + seed)
    doa = exact["doa"].copy()
    sig = np.where(rng.random(len(doa)) < share, wild * sig_deg, sig_deg)
    u = doa[["ux", "uy", "uz"]].to_numpy(float).copy()
    w = rng.normal(0.0, 1.0, u.shape) * np.radians(sig)[:, None]
    w -= np.einsum("ka,ka->k", w, u)[:, None] * u   # (a turn about the direction itself does not move it)
    doa[["ux", "uy", "uz"]] = Rotation.from_rotvec(w).apply(u)
    doa["sigma_deg"] = sig
    ring = [[0.0463 * np.cos(a), 0.0463 * np.sin(a), 0.0] for a in np.arange(6) * np.pi / 3]
    meta = {**feats["meta"], "sigma_doa_deg": sig_deg, "mics": {a: ring for a in feats["meta"]["arrays"]}}
    return feats.replace(doa=doa, meta=meta), truth


def test_planar_rows_of_unequal_sigma_each_claim_their_own_error():
    """Issue 27's orientation over-naming (h54o): the planar model took the mean square of an array's in-plane
    residuals (radians) as every row's error, so beside a few rows of a large sigma the precise rows claimed
    the imprecise rows' error through their own, large, influence (lshape 500's A4: 6° std, 0.6° error). Each row's
    own residual (leverage-corrected) is what it errs by: over simulated scenes whose rows err at their stated
    (unequal) sigmas, the orientation error / std of the planar model (no shared terms) has a Gaussian's RMS;
    with the pooled mean it was 0.15-0.21 (std 5-7x the errors)."""
    z = []
    for seed in range(510, 514):
        feats, truth = _planar_rows_of_unequal_sigma(seed)
        cal = calibrate(feats, noise="meta")
        z += _rotation_z(cal, truth, normals=U.plane_normals(feats["meta"], cal["problem"].names))
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.7 < rms < 1.4
    assert np.max(np.abs(z)) < 4.0


def test_large_problem_raises_the_array_block_only():
    """Past the dense limit the array block gets the factors (one more Schur complement) and the sources keep
    the plain blocks: array std never below the plain (JᵀJ)⁻¹'s, source std equal to it."""
    from calib.estimator.solver import use_dense
    from calib.estimator.uncertainty import cov_diagonal, honest_covariance

    rng = np.random.default_rng(7)
    stops = np.cumsum(rng.normal(0, 0.4, (90, 3)), axis=0) * [1, 1, 0.2] + [0, 0, 1.2]
    feats, _ = simulate_features(trajectory=stops, seed=7, n_arrays=5)
    p, lay, lin = _final_linearisation(calibrate(feats))
    assert not use_dense(lay)
    plain = covariance(lin.J[lin.w > 0], lay.n, lay)
    honest = honest_covariance(p, lin, lay, cov=plain)
    arr = plain.arr_cols
    assert np.all(cov_diagonal(honest)[arr] >= cov_diagonal(plain)[arr] * (1 - 1e-9))
    assert np.any(cov_diagonal(honest)[arr] > 1.01 * cov_diagonal(plain)[arr])
    src = np.setdiff1d(np.arange(lay.n), arr)
    np.testing.assert_array_equal(cov_diagonal(honest)[src], cov_diagonal(plain)[src])


def _stops_scene(seed, n_stops=60):
    """Stops scattered over 8 × 6 m (heights 0.8–1.6 m), 1° DOA noise, odometry stated at 0.5 m (too weak to
    hold the map's rotation: the reference's DOAs do). Returns (features, truth)."""
    rng = np.random.default_rng(50 + seed)
    stops = np.column_stack([rng.uniform(0, 8, n_stops), rng.uniform(0, 6, n_stops), rng.uniform(0.8, 1.6, n_stops)])
    feats, truth = simulate_features(stops, sigma_tdoa=1e-5, sigma_doa_deg=1.0, seed=seed)
    return feats.replace(meta={**feats["meta"], "sigma_odo": 0.5}), truth


def test_reference_doa_bias_is_in_the_std(monkeypatch):
    """Every DOA of the reference turned by one rotation (a wall reflection's or a mounting error's bias, which
    no number of events averages down) turns the whole map: the other arrays move by several of the std that
    takes the rows as independent. With the shared rotation error (``shared_doa_rows``) the std covers a bias
    of 3 of its own sigma: each array's move / its std stays below 3, where without it one goes beyond."""
    feats, _ = _stops_scene(0)
    sd = np.radians(feats["meta"]["sigma_doa_deg"]) * U.SHARED_DOA_FRACTION   # the model's shared sigma
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    biased = _rotate_doas(feats, "A1", np.tile(3.0 * sd * axis, (len(feats["events"]), 1)))
    cols = ["x", "y", "z"]
    clean = calibrate(feats, noise="meta")["arrays"].set_index("array")

    def moves(fraction):
        monkeypatch.setattr(U, "SHARED_DOA_FRACTION", fraction)
        monkeypatch.setattr(U, "SHARED_DOA_SCATTER", U.SHARED_DOA_SCATTER if fraction else 0.0)
        a = calibrate(biased, noise="meta")["arrays"].set_index("array")
        others = [n for n in a.index if n != "A1"]
        return np.abs(a.loc[others, cols].to_numpy() - clean.loc[others, cols].to_numpy()) / \
            a.loc[others, [c + "_std" for c in cols]].to_numpy()

    assert moves(U.SHARED_DOA_FRACTION).max() < 3.0
    assert moves(0.0).max() > 3.0


def test_scattered_doas_share_a_rotation_in_the_orientation_std(monkeypatch):
    """Rows that scatter widely about the geometry (a corner's or an obstacle's reflections, each direction its
    own) share much of that error: measured against truth on development seeds, an array's shared DOA rotation is
    ~0.9 × its rows' own scatter about the fit (``SHARED_DOA_SCATTER``), whatever their flags. A non-reference
    array's DOAs each turned by an error of 3 × their sigma of their own plus one common rotation of 4 × their
    sigma (no row flagged): its orientation error (against the simulated truth) stays within 3 of its std on each
    axis; with the shared term of an unflagged array's median row sigma (the flag rule's 0.25) it goes beyond."""
    feats, truth = _stops_scene(0)
    sd = np.radians(feats["meta"]["sigma_doa_deg"])
    rng = np.random.default_rng(7)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    m = int((feats["doa"]["array"] == "A2").sum())
    biased = _rotate_doas(feats, "A2", 4.0 * sd * axis + 3.0 * sd * rng.standard_normal((m, 3)))
    q = truth["arrays"].set_index("array").loc["A2", ["qw", "qx", "qy", "qz"]].to_numpy(float)

    def z():
        a = calibrate(biased, noise="meta")["arrays"].set_index("array").loc["A2"]
        est = Rotation.from_quat(a[["qw", "qx", "qy", "qz"]].to_numpy(float), scalar_first=True)
        err = (Rotation.from_quat(q, scalar_first=True).inv() * est).as_rotvec()
        return np.abs(err) / a[["rx_std", "ry_std", "rz_std"]].to_numpy(float)

    assert z().max() < 3.0
    monkeypatch.setattr(U, "SHARED_DOA_SCATTER", 0.0)
    assert z().max() > 3.0


def _rotation_z(cal, truth, normals=None, lower=True):
    """Each non-reference array's orientation error (about its own axes) over its std from the sandwich
    covariance with the covariance factors (``lower`` as ``covariance_factors``) and no shared terms."""
    p, lay, lin = _final_linearisation(cal)
    cov = covariance(lin.J[lin.w > 0], lay.n, lay)
    sd = np.sqrt(np.diag(U.sandwich_covariance(p, lin, cov, covariance_factors(p, lin, cov, lower=("doa",) if lower else ()), False,
                                               normals)))
    t = truth["arrays"].set_index("array")
    z = []
    for i, name in enumerate(p.names):
        if i == p.ref:
            continue
        q = t.loc[name, ["qw", "qx", "qy", "qz"]].to_numpy(float)
        err = (Rotation.from_quat(q, scalar_first=True).inv() * Rotation.from_matrix(cal["state"].R[i])).as_rotvec()
        z += list(err / sd[lay.rot[i]])
    return z


def test_stated_doa_sigma_wider_than_the_errors_is_lowered_in_the_std():
    """DOAs whose stated sigma (a frontend's own figure, which the solve never lowers) is 3× their real noise:
    the DOA rows' covariance factor recovers (1/3)² from the residuals, and the orientation errors over their std
    then have an RMS near 1 (a Gaussian's); with the factors held ≥ 1 it was 0.52 (the TDOAs hold the orientations too)."""
    z = {True: [], False: []}
    factors = []
    for seed in range(4):
        feats, truth = simulate_features(3, sigma_tdoa=SIGMA, sigma_doa_deg=1.0, seed=seed)
        meta = {**feats["meta"], "sigma_doa_deg": 3.0 * feats["meta"]["sigma_doa_deg"],
                "sigmas_estimated": ["sigma_doa_deg"]}
        cal = calibrate(feats.replace(meta=meta))
        p, lay, lin = _final_linearisation(cal)
        factors.append(covariance_factors(p, lin, covariance(lin.J[lin.w > 0], lay.n, lay), lower=("doa",))["doa"])
        for lower in (True, False):
            z[lower] += _rotation_z(cal, truth, lower=lower)
    factors = np.concatenate(factors)
    assert np.all(factors > 1 / 9 - 1e-9) and 1 / 9 <= np.median(factors) < 0.3   # (1/3)² = 0.11, the floor
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    assert 0.7 < rms[True] < 1.35
    assert rms[False] < 0.65


def _positions(cal):
    return cal["arrays"].set_index("array")[["x", "y", "z"]].to_numpy(float)


def test_a_shared_doa_rotation_moves_positions_only_through_the_reference():
    """Where the shared DOA rotation term widens the position std (issue 27's over-naming): a rotation common to a
    non-reference array's DOAs is its orientation's (R_i Exp(φ) fits the turned rows exactly, nothing else moves),
    so no array's position moves, in the re-solve and in the covariance; the reference's orientation is the gauge,
    so its DOAs' common rotation turns the map and moves every other array, by what the final linearisation predicts
    (−H⁻¹ Jᵀ Δr, Δr the turned rows' whitened change B [u]× ω / σ). Its width in the std is the reference's term."""
    feats, _ = _stops_scene(0)
    clean = calibrate(feats, noise="meta")
    omega = np.radians(2.0) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    turned = {a: calibrate(_rotate_doas(feats, a, np.tile(omega, (len(feats["events"]), 1))), noise="meta")
              for a in ("A1", "A2")}
    assert np.abs(_positions(turned["A2"]) - _positions(clean)).max() < 1e-4
    p, lay, lin = _final_linearisation(clean)
    keep = lin.w > 0
    cov = covariance(lin.J[keep], lay.n, lay)
    shared = U.shared_doa_rows(p, lin, {})
    own = shared.copy()
    own[:, 3 * p.ref:3 * p.ref + 3] = 0.0           # the non-reference arrays' blocks alone
    x = lay.x[[i for i in range(p.N) if i != p.ref]].ravel()
    moved = np.diag(U.sandwich_covariance(p, lin, cov, {}, False, None, None, own) - U.sandwich_covariance(
        p, lin, cov, {}, False))[x]
    assert np.abs(moved).max() < 1e-8      # (0.1 mm)²: only through u ≠ v at the estimate
    start = sum(len(f.r) for f in lin.factors[:[f.kind for f in lin.factors].index("doa")])
    k = np.flatnonzero(keep[start:start + 3 * len(p.doa.u)].reshape(-1, 3).all(axis=1) & (p.doa.arr == p.ref))
    u = p.doa.u[k]
    ux = np.zeros((len(k), 3, 3))
    ux[:, 0, 1], ux[:, 0, 2], ux[:, 1, 2] = -u[:, 2], u[:, 1], -u[:, 0]
    ux -= np.transpose(ux, (0, 2, 1))
    sig = np.broadcast_to(lin.factors[[f.kind for f in lin.factors].index("doa")].row_sigma, (3 * len(p.doa.u),))
    dr = np.zeros(len(lin.r))
    rows = start + 3 * k[:, None] + np.arange(3)
    dr[rows] = np.einsum("kab,kbc,c->ka", p.doa.axes[k], ux, omega) / sig[rows]
    J = np.asarray(lin.J)
    predicted = -(cov @ (J[keep].T @ dr[keep]))[x].reshape(-1, 3)
    actual = (_positions(turned["A1"]) - _positions(clean))[[i for i in range(p.N) if i != p.ref]]
    assert np.linalg.norm(actual, axis=1).min() > 0.05      # 2° at metres: centimetres
    np.testing.assert_allclose(predicted, actual, atol=0.15 * np.abs(actual).max())


def test_an_arrays_own_doa_errors_move_its_position_as_the_linearisation_predicts():
    """benchmarks/diag_own_doa.py's instrument (issue 27: do an array's own DOA errors move its position by more than
    their share of its std?): errors of a non-reference array's DOAs that are not one common rotation (each event's
    its own turn, which the orientation cannot absorb) move its position in the re-solve by what the final
    linearisation predicts, −H⁻¹ Jᵀ Δr (Δr = −B Δu / σ, the rows' whitened change). Within the rows' noise (turns of
    0.5° on 1° rows); at 1.5° the re-solve moves 1.3× the prediction and at 3° elsewhere (its robust weights)."""
    feats, _ = _stops_scene(0)
    clean = calibrate(feats, noise="meta")
    rotvecs = np.random.default_rng(7).normal(0.0, np.radians(0.5), (len(feats["events"]), 3))
    turned = calibrate(_rotate_doas(feats, "A2", rotvecs), noise="meta")
    p, lay, lin = _final_linearisation(clean)
    i = list(map(str, p.names)).index("A2")
    keep = lin.w > 0
    cov = covariance(lin.J[keep], lay.n, lay)
    start = sum(len(f.r) for f in lin.factors[:[f.kind for f in lin.factors].index("doa")])
    k = np.flatnonzero(p.doa.arr == i)
    k = k[np.argsort(p.doa.ev[k], kind="stable")]          # event order, as _rotate_doas turns them
    du = Rotation.from_rotvec(rotvecs).apply(p.doa.u[k]) - p.doa.u[k]
    sig = np.broadcast_to(lin.factors[[f.kind for f in lin.factors].index("doa")].row_sigma, (3 * len(p.doa.u),))
    rows = start + 3 * k[:, None] + np.arange(3)
    dr = np.zeros(len(lin.r))
    dr[rows] = -np.einsum("kab,kb->ka", p.doa.axes[k], du) / sig[rows - start]
    predicted = -(cov @ (np.asarray(lin.J)[keep].T @ dr[keep]))[lay.x[i]]
    actual = _positions(turned)[i] - _positions(clean)[i]
    assert np.linalg.norm(actual) > 0.0005       # half a millimetre at least: the test sees the move
    np.testing.assert_allclose(predicted, actual, atol=0.15 * np.abs(actual).max())


def test_std_sources_add_up_to_the_stated_std():
    """benchmarks/diag_std_sources.py's instrument (issue 27's over-naming: which terms make an array's std): the
    terms it splits the honest covariance's B into (arrivals, planar/own rows, shared rotations, per array) add
    up to each array's stated position variance, as calibrate reports it (x/y/z_std)."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from diag_std_sources import std_parts

    feats, _ = _stops_scene(0)
    feats = feats.replace(meta={**feats["meta"], "tdoa_shared_arrivals": True})
    cal = calibrate(feats, noise="meta")
    p, lay, lin = _final_linearisation(cal)
    cov = covariance(lin.J[lin.w > 0], lay.n, lay)
    parts, honest, _, _ = std_parts(p, lin, lay, cal["state"], cov, feats["meta"], None)
    assert {t.split(":")[0] for t in parts} >= {"shared_doa", "arrival"}
    std = cal["arrays"].set_index("array")
    for i, a in enumerate(map(str, p.names)):
        if i == p.ref:
            continue
        H = cov[:, lay.x[i]]
        var = sum(np.sum((g @ H) ** 2, axis=0) for g in parts.values())
        np.testing.assert_allclose(np.sqrt(var), std.loc[a, ["x_std", "y_std", "z_std"]].to_numpy(float), rtol=1e-6)


def test_true_shared_rotation_recovers_a_planted_rotation_and_its_noise():
    """benchmarks/diag_shared_predictors.py's instrument (issue 27: what an array's DOAs truly share): directions
    turned by one planted rotation and each then by its own noise (anisotropic sizes per row, 1°-3°); the rotation
    it reads against the true directions is the planted one within the noise it states, which is the spread of
    its reading over draws (per axis error / stated noise RMS within 0.85-1.15 over 400 draws)."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from diag_shared_predictors import true_shared_rotation

    rng = np.random.default_rng(11)
    n = 16
    u_true = rng.standard_normal((n, 3))
    u_true /= np.linalg.norm(u_true, axis=1, keepdims=True)
    size = np.radians(rng.uniform(1.0, 3.0, n))
    planted = np.radians([2.0, -1.0, 3.0])
    z = []
    for _ in range(400):
        turned = Rotation.from_rotvec(-planted).apply(u_true)   # the measured directions: ω turns them back
        kick = rng.standard_normal((n, 3)) * size[:, None]
        kick -= np.einsum("ka,ka->k", kick, turned)[:, None] * turned   # tangential noise
        u = turned + kick
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        w, noise = true_shared_rotation(u, u_true)
        z.append((w - planted) / noise)
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.85) & (rms < 1.15)), rms
