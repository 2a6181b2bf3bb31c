"""calib.geometry: the shared mirror, yaw and clock formulas against hand-derived values."""
import numpy as np

from calib.geometry import arrival_time, fold, local_time, mirror, yaw_matrix, yaw_rotate


def test_mirror_and_fold_across_a_plane():
    n = np.array([0.0, 0.0, 1.0])
    u = np.array([[0.6, 0.0, -0.8], [0.0, 0.6, 0.8]])
    assert np.allclose(mirror(u, n), [[0.6, 0.0, 0.8], [0.0, 0.6, -0.8]])
    assert np.allclose(fold(u, n), [[0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    assert np.allclose(fold(u, np.stack([n, -n])), [[0.6, 0.0, 0.8], [0.0, 0.6, -0.8]])  # one normal per row
    assert np.allclose(mirror(np.array([1.0, 2.0, 5.0]), n, origin=np.array([0.0, 0.0, 2.0])), [1.0, 2.0, -1.0])


def test_yaw_rotation_matches_its_matrix_for_one_and_many_yaws():
    v = np.random.default_rng(0).normal(size=(4, 3))
    assert np.allclose(yaw_matrix(np.pi / 2) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    psis = np.array([0.3, -1.2])
    many = yaw_rotate(v, psis)
    assert many.shape == (2, 4, 3)
    for k, psi in enumerate(psis):
        assert np.allclose(many[k], v @ yaw_matrix(psi).T) and np.allclose(yaw_rotate(v, psi), many[k])


def test_clock_model():
    # L(t) = (1 + δ)(t − t0) + τ; a = L(t + d/c) + β δ
    assert np.isclose(local_time(12.0, 0.5, 1e-3, t0=2.0), 1.001 * 10.0 + 0.5)
    assert np.isclose(arrival_time(2.0, 34.0, 0.1, 2e-4, 340.0, beta=0.25), 1.0002 * 2.1 + 0.1 + 0.25 * 2e-4)
