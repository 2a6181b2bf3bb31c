"""Any array geometry (issue 10 item 4): what each geometry measures (frontend), the simulator's per-array
mic geometries, the calibration of mic pairs from simulated recordings, and per-parameter observability."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.errors import InputError
from calib.frontend.doa import cone_vectors, fibonacci_sphere, mic_geometry, srp_cone
from calib.pipeline import roomsim as rs
from calib.pipeline.scenes import named_mics

C = 343.0


# ----------------------------------------------------------------------------------------------- frontend
@pytest.mark.parametrize("mics, kind", [
    ([[0, 0, 0]], "single"),
    ([[-0.05, 0, 0], [0.05, 0, 0]], "linear"),
    ([[0, -0.03, 0.01], [0, 0.0, 0.01], [0, 0.06, 0.01]], "linear"),
    (named_mics("circle", None, 6, 0.0354, 0), "planar"),
    (named_mics("octahedron", None, 6, 0, 0), "volume"),
])
def test_mic_geometry_kinds(mics, kind):
    k, vec = mic_geometry(mics)
    assert k == kind
    m = np.asarray(mics, float)
    if kind == "linear":   # the axis: unit, along the mics' line, largest component positive
        d = m - m.mean(0)
        assert np.isclose(np.linalg.norm(vec), 1) and np.allclose(np.cross(d, vec), 0, atol=1e-12)
        assert vec[np.argmax(np.abs(vec))] > 0
    if kind == "planar":
        assert np.allclose((m - m.mean(0)) @ vec, 0, atol=1e-12)


@pytest.mark.parametrize("mics", [[[-0.05, 0, 0], [0.05, 0, 0]],                      # 2-mic pair on x
                                  [[0.01, -0.045, 0.02], [0.01, 0.0, 0.02], [0.01, 0.045, 0.02]]])  # off-origin line
def test_srp_cone_measures_the_angle_to_the_axis(mics):
    # ideal gated spectra of a plane wave from u (mic m leads the origin by u·m / c), with noise: the cone
    # angle is measured, whatever the direction's azimuth about the axis
    mics = np.asarray(mics, float)
    _, axis = mic_geometry(mics)
    freqs = np.linspace(500, 4000, 57)
    u_true = fibonacci_sphere(60)
    rng = np.random.default_rng(1)
    g = np.exp(2j * np.pi * freqs[None, None, :] * (u_true @ mics.T)[:, :, None] / C)
    g *= np.exp(1j * rng.normal(0, 0.05, g.shape))
    cos_t, power = srp_cone(g, mics, axis, freqs, C)
    err = np.degrees(np.abs(np.arccos(cos_t) - np.arccos(u_true @ axis)))
    assert np.median(err) < 0.5 and err.max() < 3.0
    assert np.all(power > 0.9)
    u = cone_vectors(axis, cos_t)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0)
    np.testing.assert_allclose(u @ axis, cos_t, atol=1e-12)


# ----------------------------------------------------------------------------------------------- simulator
def test_scenario_geometries_per_array():
    sc = rs.make_scenario("paper-traj3", seed=2, n_arrays=5, mic_spacing=0.08,
                          geometries=["octahedron", "pair", "linear", "single"])
    mics = [np.asarray(a["mics"]) for a in sc["arrays"]]
    assert [len(m) for m in mics] == [6, 2, 6, 1, 6]
    assert mic_geometry(mics[0])[0] == "volume" and mic_geometry(mics[4])[0] == "planar"   # A5: default
    for m in mics[1:3]:
        assert mic_geometry(m) == ("linear", pytest.approx(np.array([1.0, 0, 0])))
        assert np.allclose(np.diff(m[:, 0]), 0.08) and np.allclose(m.mean(0), 0)
    rs.validate_scenario(sc)
    # the arrays' poses do not depend on their mic geometry
    base = rs.make_scenario("paper-traj3", seed=2, n_arrays=5)
    assert [a["position"] for a in base["arrays"]] == [a["position"] for a in sc["arrays"]]
    with pytest.raises(InputError, match="unknown geometry 'triangle'"):
        rs.make_scenario("paper-traj3", geometries=["triangle"])
    with pytest.raises(InputError, match="at most n_arrays"):
        rs.make_scenario("paper-traj3", n_arrays=2, geometries=["pair"] * 3)
