"""Issue 27: the frontend's ``doa_reflection`` flag (a strong reflection inside the DOA gate, close behind the
direct path) answers the room, not the source's motion during the sweep.

Truth is the simulator's: the same scene rendered with the robot moving during each sweep (0.3-0.6 m/s: Doppler,
a bearing sweep of a few degrees) and as its stopped twin (the source held at each sweep start), and free field
(rt60 0: no reflection at all); the close reflections are the box room's first-order images.
"""
import numpy as np
import pytest

SEED = 531            # development seed (500-599)
GATE_S = 1.25e-3      # the DOA gate's reach behind the direct path on these boards (16 kHz, 6-mic circle, 0.5-4 kHz):
                      # n_pulse + taper + half = 5 + 10 + 5 samples (frontend.extract._direct_path_doa)
MARGIN_S = 0.25e-3    # a pulse width and a little: the envelope's peak of a reflection merged with the direct path


def _flags(sc, folder):
    from calib.pipeline.features import session_features
    from calib.pipeline.simulate.roomsim import simulate

    feats, _ = session_features(simulate(sc, folder))
    d = feats["doa"]
    return d.set_index(["event", "array"])["flag"].fillna("").astype(str).str.contains("doa_reflection")


def _first_image_delay(sc, event, array):
    """Seconds by which the earliest first-order image (six walls of the box room) trails the direct path."""
    room = np.asarray(sc["room_dim"], float)
    x = np.asarray(sc["sources"][event], float)
    p = np.asarray(next(a["position"] for a in sc["arrays"] if a["name"] == array), float)
    direct = np.linalg.norm(x - p)
    images = []
    for k in range(3):
        for wall in (0.0, room[k]):
            xi = x.copy()
            xi[k] = 2 * wall - x[k]
            images.append(np.linalg.norm(xi - p) - direct)
    return min(images) / sc["speed_of_sound"]


@pytest.mark.slow
def test_doa_reflection_flag_follows_the_room_not_the_motion(tmp_path):
    from calib.pipeline.simulate.roomsim import make_scenario

    moving = make_scenario("moving", SEED, n_events=10)
    stopped = {k: v for k, v in moving.items() if k != "trajectory"}   # sources = the sweep starts
    free = make_scenario("moving", SEED, n_events=10, rt60=0.0)
    f_mv, f_st, f_free = _flags(moving, tmp_path / "mv"), _flags(stopped, tmp_path / "st"), _flags(free, tmp_path / "ff")

    # no reflection, the robot moving: nothing flagged (Doppler and the bearing sweep are not a reflection)
    assert not f_free.any(), f_free[f_free]
    # the same room moving or stopped: the same rows flagged (measured 24 / 25 of 48 on this seed, 98 % agreeing)
    j = f_mv.to_frame("mv").join(f_st.to_frame("st"), how="inner")
    assert len(j) >= 0.9 * len(f_mv) and j.mv.sum() >= 5
    assert (j.mv == j.st).mean() >= 0.9 and abs(int(j.mv.sum()) - int(j.st.sum())) <= 0.1 * len(j)
    # against the images: a flagged row has a real reflection inside the gate; a row without one is never flagged
    delay = np.array([_first_image_delay(stopped, e, a) for e, a in j.index])
    assert np.all(delay[j.mv.to_numpy()] < GATE_S + MARGIN_S), delay[j.mv.to_numpy()]
    far = delay > GATE_S + MARGIN_S
    assert far.sum() >= 5 and not j.mv.to_numpy()[far].any()
