"""benchmarks/diag_doa_field.py's instrument against planted fields (issue 27's ceiling-array diagnosis)."""
import importlib.util
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location(
    "diag_doa_field", Path(__file__).parents[1] / "benchmarks" / "diag_doa_field.py")
F = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(F)

NOISE = np.deg2rad(0.3)   # per-component DOA noise (rad), moving-preset A3's scale


def _geometry(rng, n=20):
    """Sources 1.5-5 m away, 30-80° above a planar board's plane (array frame), as on the moving preset."""
    el, az = rng.uniform(np.deg2rad(30), np.deg2rad(80), n), rng.uniform(-np.pi, np.pi, n)
    u = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    return u, rng.uniform(1.5, 5.0, n)


def _measure(rng, u, du):
    T = F.tangent(u)
    um = u + du + np.einsum("nij,ni->nj", T, rng.normal(0, NOISE, (len(u), 2)))
    return um / np.linalg.norm(um, axis=1, keepdims=True)


def test_planted_displacement_is_found_and_measured():
    """A displacement-like field (the array 5 cm off in its plane) is the pose model's, not a scale's."""
    rng = np.random.default_rng(0)
    u, d = _geometry(rng, 60)
    dx = np.array([0.05, -0.02, 0.0])
    fits, _ = F.fit_fields(u, _measure(rng, u, np.einsum("nij,j->ni", F.fields(u, d)["pos"], dx)), d)
    assert fits["pose"]["p_value"] < 1e-4
    assert np.linalg.norm(np.array(fits["pose"]["c"][3:6]) - dx) < 0.02
    assert fits["pose+k"]["p_value"] > 1e-3


def test_planted_scale_is_found_and_measured():
    """An in-plane aperture error k = -2 % (elevation pulled toward the normal) is the scale model's."""
    rng = np.random.default_rng(1)
    u, d = _geometry(rng, 60)
    fits, _ = F.fit_fields(u, _measure(rng, u, -0.02 * F.fields(u, d)["scale"][:, :, 0]), d)
    assert fits["rot+k"]["p_value"] < 1e-4
    assert abs(fits["rot+k"]["c"][3] + 0.02) < 0.005


def test_independent_noise_reads_as_chance():
    """Pure independent noise: the F tests' p-values are uniform (few below 1 %)."""
    rng = np.random.default_rng(2)
    small = []
    for _ in range(40):
        u, d = _geometry(rng)
        fits, _ = F.fit_fields(u, _measure(rng, u, 0.0), d)
        small += [fits[m]["p_value"] < 0.01 for m in ("rot+k", "pose", "rot+lin")]
    assert np.mean(small) < 0.06


def test_stated_sigma_weights_the_rows():
    """With each row's stated sd the F tests read the same planted displacement, and noise at chance."""
    rng = np.random.default_rng(3)
    u, d = _geometry(rng, 60)
    sigma = np.full(len(u), NOISE)
    dx = np.array([0.0, 0.04, 0.0])
    fits, _ = F.fit_fields(u, _measure(rng, u, np.einsum("nij,j->ni", F.fields(u, d)["pos"], dx)), d, sigma=sigma)
    assert fits["pose"]["p_value"] < 1e-4 and np.linalg.norm(np.array(fits["pose"]["c"][3:6]) - dx) < 0.02
    fits, _ = F.fit_fields(u, _measure(rng, u, 0.0), d, sigma=sigma)
    assert fits["pose"]["p_value"] > 1e-3
