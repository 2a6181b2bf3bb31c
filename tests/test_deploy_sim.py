"""The simulator's deployment conditions (issue 27): non-convex rooms with line-of-sight truth, a speaker
moving while it chirps (time-varying delay, Doppler), mixed boards and rates, obstacles, the presets."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import soundfile as sf

from calib.pipeline.simulate import acoustics as ac
from calib.pipeline.simulate import polyroom
from calib.pipeline.simulate.clocks import fault_clock
from calib.pipeline.simulate.presets import DEPLOY, ISSUE27_SCENES, PRESETS
from calib.pipeline.simulate.roomsim import make_scenario, simulate, validate_scenario
from calib.pipeline.simulate.simrender import line_of_sight
from calib.pipeline.simulate.sounds import chirp_signal

C = 343.0
L_ROOM = [[0, 0], [8, 0], [8, 4], [4, 4], [4, 8], [0, 8]]   # an L: the corner (4, 4) hides one arm from the other
QUIET = {"snr": math.inf, "diffuse_snr": math.inf, "hum_snr": math.inf, "gain_mismatch_db": 0.0,
         "directivity": "omni", "air_absorption": False}


# ----------------------------------------------------------------------------------------------- geometry
def test_line_of_sight_matches_hand_geometry():
    """Walls between source and mic, by hand: from (6, 2) the line to (2, 6.5) meets y = 4 at t = 4/9, x = 4.22:
    on the wall y = 4, 4 ≤ x ≤ 8 (the inner side of the lower arm), blocked; to (1, 7.5) at x = 4.18, blocked;
    (2, 2) and (6, 3.5) are in view; (6, 6) is the quadrant the L leaves out."""
    geo = polyroom.make_geometry(L_ROOM, 3.0)
    src = np.array([6.0, 2.0, 1.2])
    pts = np.array([[2.0, 6.5, 1.2], [2.0, 2.0, 1.0], [6.0, 3.5, 2.0], [1.0, 7.5, 1.0]])
    los = polyroom.direct_gain(geo, src, pts)[:, 0] > 0
    assert los.tolist() == [False, True, True, False]
    assert not polyroom.inside(geo, np.array([[6.0, 6.0, 1.0]]))[0]
    assert polyroom.inside(geo, np.array([[2.0, 6.5, 1.0], [6.0, 2.0, 1.0]])).all()


def test_obstacle_attenuates_crossing_paths_only():
    """A panel x = 3, 1 ≤ y ≤ 3, 0 ≤ z ≤ 2 m with a 12 dB loss: the path through it loses 12 dB, paths that
    pass beside it or over it nothing."""
    geo = polyroom.make_geometry([[0, 0], [6, 0], [6, 5], [0, 5]], 3.0,
                                 [{"p0": [3.0, 1.0], "p1": [3.0, 3.0], "z": [0.0, 2.0], "loss_db": np.full(7, 12.0)}])
    low = polyroom.direct_gain(geo, np.array([1.0, 2.0, 1.0]), np.array([[5.0, 2.0, 1.0], [5.0, 4.5, 1.0]]))
    high = polyroom.direct_gain(geo, np.array([1.0, 2.0, 2.5]), np.array([[5.0, 2.0, 2.5]]))
    assert np.allclose(low[0], 10 ** (-12 / 20)) and np.allclose(low[1], 1.0) and np.allclose(high, 1.0)


def test_image_visibility_in_a_box_equals_the_shoebox_images():
    """In a convex room every image is visible: the polygonal image sources (with visibility) of a 4-corner
    floor plan must be exactly the shoebox images of order ≤ 3 (an independent construction)."""
    rng = np.random.default_rng(3)
    room = np.array([6.0, 5.0, 3.0])
    geo = polyroom.make_geometry([[0, 0], [6, 0], [6, 5], [0, 5]], 3.0)
    src = rng.uniform(0.5, room - 0.5)
    mics = rng.uniform(0.5, room - 0.5, (3, 3))
    tree = polyroom.image_tree(geo, src, 3)
    vis = polyroom.path_gains(geo, tree, mics)[..., 0] > 0
    sb = ac.shoebox_images(src, room, src, 200.0)
    sel = sb["hits"].sum(axis=1) <= 3
    for m in range(len(mics)):
        d_poly = np.sort(np.linalg.norm(tree["pos"][vis[:, m]] - mics[m], axis=1))
        d_box = np.sort(np.linalg.norm(sb["pos"][sel] - mics[m], axis=1))
        assert d_poly.shape == d_box.shape and np.allclose(d_poly, d_box)


def _array(name, pos, tau=0.3, drift=0.0, mics=((0.0, 0.0, 0.0),)):
    return {"name": name, "position": list(pos), "mics": [list(m) for m in mics], "tau": tau, "drift": drift}


def test_blocked_array_hears_only_reflections(tmp_path):
    """Anechoic L-shaped room: the array behind the corner receives nothing (no reflections exist), the one
    in view receives the direct path at the analytic time; truth/los.csv says which."""
    sc = make_scenario("lab", 0, model="bands", rt60=0.0, room_dim=[8.0, 8.0, 3.0], floor_plan=L_ROOM,
                       sources=[[6.0, 2.0, 1.2]], t_emit=[0.5], **QUIET,
                       arrays=[_array("A1", [2.0, 2.0, 1.0]), _array("A2", [2.0, 6.5, 1.2])])
    out = simulate(sc, tmp_path / "s")
    seen, fs = sf.read(out / "A1.wav")
    hidden, _ = sf.read(out / "A2.wav")
    assert np.max(np.abs(seen)) > 0.1 and np.max(np.abs(hidden)) == 0.0
    los = pd.read_csv(out / "truth" / "los.csv")
    assert los["los"].tolist() == [1, 0] and los["cause"].fillna("").tolist() == ["", "wall"]
    # with walls that reflect, A2 hears reflections only: its first arrival is later than the direct path
    sc2 = {**sc, "rt60": 0.4}
    v = validate_scenario(sc2)
    tab = line_of_sight(v)
    assert tab["los"].tolist() == [1, 0] and np.isnan(tab["direct_minus_reflection_db"].iloc[1])


# ----------------------------------------------------------------------------------------------- motion
def _moving(v, drift, fs=16000, **extra):
    s0, r = np.array([2.0, 3.0, 1.5]), np.array([5.0, 3.5, 1.4])
    tt = np.linspace(0.0, 3.0, 31)
    traj = {"t": tt.tolist(), "pos": (s0 + np.outer(tt - 0.5, v)).tolist()}
    sc = make_scenario("lab", 0, model="bands", rt60=0.0, room_dim=[8.0, 6.0, 3.0], fs=fs, **QUIET,
                       sources=[s0.tolist()], t_emit=[0.5], trajectory=traj,
                       arrays=[_array("A1", r, tau=0.3, drift=drift)], **extra)
    return sc, s0, r


def _retarded(sc, s0, r, v, n, fs, T=None):
    """Closed form: a constant-velocity source, |s0 + v (t_e − t_j) − r| = c (T − t_e), T the true time of
    sample n on the array's drifting clock (given: on a faulty one)."""
    a = sc["arrays"][0]
    if T is None:
        T = 0.5 + (n / fs - a["tau"]) / (1 + a["drift"])
    w = s0 - r - v * 0.5
    qa, qb, qc = v @ v - C ** 2, 2 * (w @ v) + 2 * C ** 2 * T, w @ w - C ** 2 * T ** 2
    te = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    return te, C * (T - te)


def test_moving_source_matches_the_retarded_time_closed_form(tmp_path):
    """Free field, a speaker moving at 0.6 m/s during the sweep, a drifting clock: the recording equals the
    chirp evaluated at the analytic emission time over the analytic distance (Doppler included) up to
    float32 precision, while a static speaker at the sweep's start is far off."""
    v = np.array([0.45, -0.3, 0.1])
    sc, s0, r = _moving(v, 4e-5)
    y, fs = sf.read(simulate(sc, tmp_path / "m") / "A1.wav")
    te, d = _retarded(sc, s0, r, v, np.arange(len(y)), fs)
    ref = chirp_signal(te - 0.5, sc["chirp"]) / d
    k = (ref @ y) / (ref @ ref)
    assert np.max(np.abs(y - k * ref)) < 1e-5 * np.max(np.abs(k * ref))
    d0 = np.linalg.norm(s0 - r)
    T = 0.5 + (np.arange(len(y)) / fs - 0.3) / (1 + 4e-5)
    static = chirp_signal(T - d0 / C - 0.5, sc["chirp"]) / d0
    ks = (static @ y) / (static @ static)
    assert np.max(np.abs(y - ks * static)) > 0.3 * np.max(np.abs(y))
    # the recording's instantaneous frequency (analytic signal) is the emitted one times the Doppler factor
    # 1 / (1 − v·u / c) (u: source → mic), on the array's clock (÷ (1 + δ))
    from scipy.signal import hilbert

    f_inst = np.diff(np.unwrap(np.angle(hilbert(y)))) * fs / (2 * np.pi)
    ch = sc["chirp"]
    for frac in (0.3, 0.5, 0.7):
        n = int(np.argmin(np.abs(te - 0.5 - frac * ch["duration"])))
        s_e = s0 + v * (te[n] - 0.5)
        u = (r - s_e) / np.linalg.norm(r - s_e)
        f_emit = ch["f0"] + (ch["f1"] - ch["f0"]) * (te[n] - 0.5) / ch["duration"]
        expected = f_emit / (1 - v @ u / C) / (1 + 4e-5)
        measured = np.mean(f_inst[n - 40:n + 40])
        assert abs(measured - expected) < 0.1 * abs(expected - f_emit / (1 + 4e-5))


@pytest.mark.parametrize("size, at", [(0.005, -0.2), (-0.003, 0.008 + 0.25)])
def test_a_moving_source_is_recorded_on_the_array_s_faulty_clock(tmp_path, size, at):
    """A block of samples inserted before the sweep, or dropped while it arrives (``at``: s after the
    emission): every sample equals the closed form at the true time the faulty clock gives it (the inverse
    of its local time), as a static source's recording does — not the clean clock's (the direct path 5 ms or
    3 ms off, which the truth's clock would then misstate)."""
    v = np.array([0.45, -0.3, 0.1])
    fault = {"steps": [{"size": size, "time": at}]}
    sc, s0, r = _moving(v, 4e-5, clock_faults={"A1": fault})
    clk = fault_clock(0.3, 4e-5, fault, event_times=[0.0], rng=None, t0=0.5)   # the clock attached when rendering
    y, fs = sf.read(simulate(sc, tmp_path / "m") / "A1.wav")
    n = np.arange(len(y))
    for T, fits in ((clk.emitter(n / fs), True), (None, False)):
        te, d = _retarded(sc, s0, r, v, n, fs, T)
        ref = chirp_signal(te - 0.5, sc["chirp"]) / d
        k = (ref @ y) / (ref @ ref)
        assert (np.max(np.abs(y - k * ref)) < 1e-4 * np.max(np.abs(y))) == fits


@pytest.mark.slow
def test_events_carry_the_velocity_at_the_sweep_start(tmp_path):
    sc = make_scenario("moving", 2, n_events=3, rt60=0.3, sigma_vel=0.0, sigma_odo=0.0)
    out = simulate(sc, tmp_path / "m")
    ev = pd.read_csv(out / "events.csv")
    tr = pd.read_csv(out / "truth" / "trajectory.csv")
    src = pd.read_csv(out / "truth" / "sources.csv")
    vel = np.gradient(tr[["x", "y", "z"]].to_numpy(), tr["t"].to_numpy(), axis=0)   # finite differences
    for j, t in enumerate(ev["t_emit"]):
        i = int(np.argmin(np.abs(tr["t"] - t)))
        assert np.allclose(ev.loc[j, ["vel_x", "vel_y", "vel_z"]].to_numpy(float), vel[i], atol=5e-3)
        # the event's position is the sweep START (odometry and truth agree)
        assert np.allclose(ev.loc[j, ["odom_x", "odom_y", "odom_z"]].to_numpy(float),
                           src.loc[j, ["x", "y", "z"]].to_numpy(float) - src.loc[0, ["x", "y", "z"]].to_numpy(float),
                           atol=1e-9)


# ----------------------------------------------------------------------------------------------- presets
@pytest.mark.slow
@pytest.mark.parametrize("preset", DEPLOY + ("occluded-lab",))
def test_deploy_presets_validate_and_vary_by_seed(preset):
    a, b = make_scenario(preset, 0), make_scenario(preset, 1)
    validate_scenario(a), validate_scenario(b)
    assert a["sources"] != b["sources"] and a["arrays"] != b["arrays"]
    assert preset in PRESETS


@pytest.mark.parametrize("preset", ["lab", "moving", "office"])
def test_a_table_override_merges_into_the_preset(preset):
    # `calib simulate --chirp-duration 1.0` (chirp={"duration": 1.0}): the chirp's band stays the preset's,
    # on the room presets and on the deployment ones (which once replaced the whole chirp table)
    base = validate_scenario(make_scenario(preset, 0))["chirp"]
    got = validate_scenario(make_scenario(preset, 0, chirp={"duration": 1.0}))["chirp"]
    assert got == {**base, "duration": 1.0} and base["duration"] != 1.0


def test_presets_hold_their_conditions():
    # non-convex room: some (array, event) pairs lose the line of sight, not all
    for seed in (0, 1):
        los = line_of_sight(validate_scenario(make_scenario("lshape", seed)))
        assert 0.05 < 1 - los["los"].mean() < 0.6
    # moving robot: drives at 0.3-0.6 m/s during every sweep (the speaker mast also moves once), events ~3 s apart
    for seed in (0, 1):
        v = validate_scenario(make_scenario("robot", seed))
        t = v["t_emit"][:, None] + np.linspace(0, v["chirp"]["duration"], 6)[None]
        speed = np.linalg.norm(v["trajectory"].velocity(t)[..., :2], axis=2)   # driving (horizontal) speed
        assert len(v["t_emit"]) == 64 and np.all((speed > 0.29) & (speed < 0.61))
        assert 2.2 < np.median(np.diff(v["t_emit"])) < 3.8
    # mixed boards and rates
    m = validate_scenario(make_scenario("office", 0))
    assert sorted({len(a["mics"]) for a in m["arrays"]}) == [2, 4, 6, 7]
    assert {a["fs"] for a in m["arrays"]} == {16000, 44100, 48000}
    for seed in range(5):       # the reference is never a linear array or a pair (sources not placeable)
        sc = make_scenario("office", seed)
        ref = next(a for a in sc["arrays"] if a["name"] == sc["reference_array"])
        assert np.linalg.matrix_rank(np.asarray(ref["mics"]) - np.mean(ref["mics"], axis=0), tol=1e-6) >= 2
    # the warehouse: size, reverberation, arrays, SNR, rate as the issue's scene
    w = validate_scenario(make_scenario("warehouse", 3))
    assert w["room_dim"].tolist() == [20.0, 15.0, 6.0] and 1.1 <= w["rt60"] <= 1.3
    assert 10 <= len(w["arrays"]) <= 12 and w["snr"] == 5.0 and w["fs"] == 16000
    # occlusion at several attenuations: the obstacles' losses and the mounts' differ by seed
    losses = {round(o["loss_db"], 1) for s in range(3) for o in make_scenario("occluded", s)["obstacles"]}
    assert len(losses) >= 4 and all(6 <= x <= 20 for x in losses)
    occ = {make_scenario("occluded-lab", s)["arrays"][1].get("direct_db") for s in range(3)}
    assert len(occ) == 3
    assert set(ISSUE27_SCENES) <= set(PRESETS)


@pytest.mark.slow
def test_a_combined_preset_renders_with_its_truth(tmp_path):
    """L/U-shaped room + moving robot + mixed boards + talkers + an obstacle, 2 events: every file and the
    truth's shapes (los.csv one row per event and array, rates per board, velocities in events.csv), and
    the manifest reproduces the session byte for byte."""
    import filecmp

    from calib.pipeline.simulate.roomsim import load_scenario

    sc = make_scenario("deploy", 1, n_events=2)
    out = simulate(sc, tmp_path / "d")
    v = validate_scenario(sc)
    for a in v["arrays"]:
        info = sf.info(out / f"{a['name']}.wav")
        assert info.samplerate == a["fs"] and info.channels == len(a["mics"])
    assert len({a["fs"] for a in v["arrays"]}) == 3
    los = pd.read_csv(out / "truth" / "los.csv")
    assert len(los) == 2 * len(v["arrays"]) and set(los.columns) >= {"event", "array", "los", "cause"}
    ev = pd.read_csv(out / "events.csv")
    assert list(ev.columns[-3:]) == ["vel_x", "vel_y", "vel_z"] and len(ev) == 2
    assert (out / "truth" / "trajectory.csv").is_file()
    again = simulate(load_scenario(out / "truth" / "manifest.json"), tmp_path / "again")
    for f in ["A1.wav", "A5.wav", "events.csv", "truth/los.csv", "truth/manifest.json"]:
        assert filecmp.cmp(out / f, again / f, shallow=False), f


@pytest.mark.parametrize("key,value,needle", [("boards", "pair", None), ("boards", "[pair,tetra]", "'[pair,tetra]'"),
                                              ("boards", ["pair", "quad9"], "'quad9'"), ("mounts", ["wall", "ceiling"],
                                                                                         "'ceiling'")])
def test_board_and_mount_names_are_checked_as_input(key, value, needle):
    """`--set boards=...` as a user types it (a bare name, TOML without quotes: a string; a misspelt board): one
    board name is that board on every array; anything else is an input error naming the value and the choices,
    never an internal error (a KeyError on the string's first character)."""
    from calib.pipeline.formats.io import InputError
    from calib.pipeline.simulate.deploy import BOARDS

    if needle is None:
        sc = make_scenario("mixed", 0, n_events=2, **{key: value})
        assert {a["board"] for a in sc["arrays"]} == {value}
        assert all(len(a["mics"]) == len(BOARDS[value][0]) for a in sc["arrays"])
        return
    with pytest.raises(InputError) as exc:
        make_scenario("mixed", 0, n_events=2, **{key: value})
    assert needle in str(exc.value) and key in str(exc.value)
