"""The DOA refinements end a direction's shrinking stencil after two fitted steps in a row shorter than the
tolerance (doa._short_step): the directions of the full shrinking schedule, against analytic plane waves,
against that schedule and against a refinement run a hundred times finer, for about half the SRP evaluations."""
from __future__ import annotations

import numpy as np
import pytest

import calib.frontend.doa as doa
from calib.frontend.doa import band_scatter, srp_cone, srp_doa, srp_setup

from .test_doa_reflection import CIRCLE6, C, angle_deg, plane_waves, reflected, unit

TETRA = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) * 0.03
LINEAR4 = np.c_[np.linspace(-0.06, 0.06, 4), np.zeros(4), np.zeros(4)]
FREQS = np.linspace(500.0, 4000.0, 57)   # a 16 kHz session's gated band (gated_spectra)
UP = np.array([0.0, 0.0, 1.0])


def _wave(u, mics):
    return plane_waves(u, mics, FREQS)


def _counted(monkeypatch):
    """The events' rows of srp_power calls made through the doa module (a refinement stencil: one per event
    still refined)."""
    calls = {"n": 0}
    inner = doa.srp_power

    def counting(g, *a, **k):
        calls["n"] += len(g)
        return inner(g, *a, **k)
    monkeypatch.setattr(doa, "srp_power", counting)
    return calls


@pytest.mark.parametrize("mics,hemisphere", [(CIRCLE6, UP), (TETRA, None)])
def test_settled_refinement_finds_plane_waves_in_few_stencils(monkeypatch, mics, hemisphere):
    rng = np.random.default_rng(5)
    u = unit(np.radians(rng.uniform(5.0, 80.0, 64)), rng.uniform(-np.pi, np.pi, 64))
    setup = srp_setup(mics, FREQS, C, 3.0, hemisphere)
    calls = _counted(monkeypatch)
    est, _ = srp_doa(_wave(u, mics), setup)
    assert angle_deg(est, u).max() < 0.005
    # the full schedule from half a 3° step down to 0.02°: 7 stencils and the power at the result
    assert calls["n"] <= 5 * len(u)


def test_settled_cone_angle_in_few_stencils(monkeypatch):
    rng = np.random.default_rng(6)
    theta = np.radians(rng.uniform(10.0, 170.0, 64))
    u = np.c_[np.cos(theta), np.sin(theta), np.zeros(64)]
    calls = _counted(monkeypatch)
    cos_t, _ = srp_cone(_wave(u, LINEAR4), LINEAR4, np.array([1.0, 0.0, 0.0]), FREQS, C)
    assert np.degrees(np.abs(np.arccos(cos_t) - theta)).max() < 0.005   # 0.01° asked
    assert calls["n"] <= 6 * len(u)   # the grid, then the full schedule: 7 stencils from 1° to 0.01°, the power


def test_settled_refinement_equals_the_full_schedule_under_a_reflection(monkeypatch):
    # a wall reflection a pulse behind the direct path (test_doa_reflection): the SRP's peak is off the truth
    # and misshapen, the sub-bands' even more; the early stop lands where the full shrinking schedule does
    # (SETTLED_STEP < 0: never settled) and where a refinement 100× finer does, in fewer stencils
    u, g = reflected(np.random.default_rng(7), 200, CIRCLE6, FREQS)
    setup = srp_setup(CIRCLE6, FREQS, C, 3.0, UP)
    calls = _counted(monkeypatch)
    est, _ = srp_doa(g, setup)
    sd = band_scatter(g, setup, est)
    n_settled = calls["n"]
    fine, _ = srp_doa(g, setup, refine_to_deg=2e-4)
    assert angle_deg(est, fine).max() < 0.005
    monkeypatch.setattr(doa, "SETTLED_STEP", -1.0)
    calls["n"] = 0
    full, _ = srp_doa(g, setup)
    sd_full = band_scatter(g, setup, full)
    assert angle_deg(est, full).max() < 0.005           # srp_doa's tolerance: 0.02°
    assert np.degrees(np.abs(sd - sd_full)).max() < 0.05   # band_scatter's: 0.1° (sub-band DOAs within 0.1° / 3)
    assert n_settled < 0.7 * calls["n"]
