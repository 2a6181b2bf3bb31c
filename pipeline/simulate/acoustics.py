"""Room acoustics beyond the flat image-source model, for the room simulator (``pipeline.simulate.roomsim``).

Everything here works on one array's sample grid (rate ``fs' = fs (1 + δ)``), in the room frame, SI units:

* :func:`shoebox_images` — image sources of a shoebox room with their reflection counts per wall, so that
  each image carries a per-octave-band amplitude (frequency-dependent wall materials, from
  ``pyroomacoustics.materials_data``) and its EMISSION direction (the direction in which the ray left the
  real source: the image direction mirrored back once per reflection on each axis);
* :func:`band_weights` — a zero-phase octave crossover whose weights sum to exactly 1 at every frequency,
  so a path with the same amplitude in every band (the direct path) is reconstructed without any filtering;
* :func:`band_rt60` — the Sabine reverberation time per band (walls + air absorption), the target decay of
  the stochastic late tail (:func:`tail_envelopes`);
* :func:`directivity_gain` — first-order (cardioid-family) speaker directivity;
* :func:`diffuse_coherence_mix` — per-frequency mixing matrices giving a set of mics the sinc spatial
  coherence of a spherically diffuse field.
"""
from __future__ import annotations

import math

import numpy as np

# Octave bands of pyroomacoustics' material tables (Hz); every material below is given on them.
BAND_CENTERS = (125.0, 250.0, 500.0, 1000.0, 2000.0, 4000.0, 8000.0)
RT60_BAND = 1000.0   # the scenario's ``rt60`` is the Sabine RT60 of this octave (the usual single-number RT60)
ALPHA_MAX = 0.95     # energy absorption is capped here after scaling a material to the target RT60
SABINE = 24 * math.log(10)  # RT60 = SABINE V / (c A), A = Σ S α + 4 m V (m: air energy attenuation, 1/m)
# pattern name → omnidirectional weight p of the gain p + (1 − p) cos θ
REAR_FLOOR_DB = -20.0  # default: a real "cardioid" loudspeaker still radiates about −20 dB backwards (no null)
PATTERNS = {"omni": 1.0, "subcardioid": 0.7, "cardioid": 0.5, "supercardioid": 0.37, "hypercardioid": 0.25}
COHERENCE_GRID = 10.0  # Hz between exact diffuse-coherence square roots (interpolated in between)
WALLS = ("west", "east", "south", "north", "floor", "ceiling")  # x = 0, x = Lx, y = 0, y = Ly, z = 0, z = Lz


# ----------------------------------------------------------------------------------------------- materials
def material_coeffs(name):
    """Energy absorption per band (7,) of a ``pyroomacoustics.materials_data`` material, or a list of 7."""
    if not isinstance(name, str):
        a = np.asarray(name, float)
        if a.shape != (len(BAND_CENTERS),) or np.any(a < 0) or np.any(a > 1):
            raise ValueError(f"a material must be a name or {len(BAND_CENTERS)} absorption coefficients in [0, 1]")
        return a
    from pyroomacoustics.parameters import materials_data

    for table in materials_data["absorption"].values():
        if name in table:
            m = table[name]
            freqs = m.get("center_freqs", materials_data["center_freqs"])
            return np.interp(np.log(BAND_CENTERS), np.log(freqs[:len(m["coeffs"])]), m["coeffs"])
    raise ValueError(f"unknown material {name!r} (see pyroomacoustics.materials_data)")


def air_attenuation():
    """Air energy attenuation per band (7,) in 1/m (pyroomacoustics, 20 °C, 50 % relative humidity)."""
    from pyroomacoustics.parameters import Physics

    a = Physics().get_air_absorption()
    return np.interp(np.log(BAND_CENTERS), np.log(a["center_freqs"]), a["coeffs"])


def wall_areas(room):
    """Areas (6,) m² of the walls in ``WALLS`` order for a shoebox ``room`` (3,)."""
    lx, ly, lz = room
    return np.array([ly * lz, ly * lz, lx * lz, lx * lz, lx * ly, lx * ly])


def scaled_absorption(materials, room, rt60, c, air=True, surfaces=None):
    """Energy absorption (6 walls, 7 bands), the materials' shapes scaled so the ``RT60_BAND`` octave has
    the Sabine reverberation time ``rt60`` (air absorption included when ``air``).

    materials : dict wall → material (name or 7 coefficients); missing walls take ``materials['walls']``.
    surfaces : (names, areas (W,), volume) of another room shape (a polygonal room: :func:`poly_surfaces`);
        default the shoebox ``room``'s six walls.
    """
    names, S, V = surfaces if surfaces is not None else (WALLS, wall_areas(room), float(np.prod(room)))
    shape = np.stack([material_coeffs(materials.get(w, materials.get("walls"))) for w in names])
    m = air_attenuation() if air else np.zeros(len(BAND_CENTERS))
    b = BAND_CENTERS.index(RT60_BAND)
    need = SABINE * V / (c * rt60) - 4 * m[b] * V       # Σ S α at the reference band
    have = float(S @ shape[:, b])
    if need <= 0 or have <= 0:
        raise ValueError(f"rt60 = {rt60:g} s is not reachable with these materials")
    alpha = shape * (need / have)
    if alpha[:, b].max() > ALPHA_MAX:
        raise ValueError(f"rt60 = {rt60:g} s is too short for this room (wall absorption > {ALPHA_MAX})")
    return np.minimum(alpha, ALPHA_MAX)


def poly_surfaces(geo):
    """(names, areas, volume) of a polygonal room (``polyroom.make_geometry``): its vertical walls are
    ``wall0``… (material ``materials['wall0']`` or ``materials['walls']``), then ``floor`` and ``ceiling``."""
    names = [f"wall{w}" for w in range(len(geo["corners"]))] + ["floor", "ceiling"]
    return names, geo["area"], geo["volume"]


def band_rt60(alpha, room, c, air=True, surfaces=None):
    """Sabine RT60 per band (7,) s for absorption ``alpha`` (6, 7) (or (W, 7) with ``surfaces``)."""
    _, S, V = surfaces if surfaces is not None else (WALLS, wall_areas(room), float(np.prod(room)))
    m = air_attenuation() if air else np.zeros(len(BAND_CENTERS))
    return SABINE * V / (c * (S @ alpha + 4 * m * V))


# ----------------------------------------------------------------------------------------------- images
def _axis_images(s, L, reach):
    """Image coordinates along one axis: (coords (n,), reflections on the near wall, on the far wall, odd)."""
    kmax = int(math.ceil(reach / (2 * L))) + 1
    k = np.arange(-kmax, kmax + 1)
    even = 2 * k * L + s                       # |k| reflections on each wall
    odd = 2 * k * L - s                        # k ≤ 0: |k| + 1 on the near wall, |k| far; k ≥ 1: k − 1, k
    near = np.r_[np.abs(k), np.where(k <= 0, np.abs(k) + 1, k - 1)]
    far = np.r_[np.abs(k), np.where(k <= 0, np.abs(k), k)]
    flip = np.r_[np.zeros(k.size, bool), np.ones(k.size, bool)]
    return np.r_[even, odd], near, far, flip


def shoebox_images(src, room, centre, reach):
    """Image sources of ``src`` within ``reach`` m of ``centre`` in a shoebox ``room`` (origin at a corner).

    Returns a dict: ``pos`` (n, 3) m, ``hits`` (n, 6) reflections per wall (``WALLS`` order), ``flip``
    (n, 3) bool (odd number of reflections on that axis: the emission direction's component is mirrored),
    ``direct`` (n,) bool (the real source). Order 0 is the real source itself.
    """
    axes = [_axis_images(src[d], room[d], reach + room[d]) for d in range(3)]
    ix, iy, iz = np.meshgrid(*[np.arange(a[0].size) for a in axes], indexing="ij")
    ix, iy, iz = ix.ravel(), iy.ravel(), iz.ravel()
    pos = np.stack([axes[0][0][ix], axes[1][0][iy], axes[2][0][iz]], axis=1)
    keep = np.linalg.norm(pos - centre, axis=1) <= reach
    ix, iy, iz, pos = ix[keep], iy[keep], iz[keep], pos[keep]
    hits = np.stack([axes[0][1][ix], axes[0][2][ix], axes[1][1][iy], axes[1][2][iy],
                     axes[2][1][iz], axes[2][2][iz]], axis=1)
    flip = np.stack([axes[0][3][ix], axes[1][3][iy], axes[2][3][iz]], axis=1)
    return {"pos": pos, "hits": hits, "flip": flip, "direct": hits.sum(axis=1) == 0}


def image_band_amplitudes(hits, alpha):
    """Pressure reflection factor per image and band (n, 7): Π_walls sqrt(1 − α_wall,band)^hits."""
    r = np.sqrt(1.0 - alpha)                                            # (6, B); 0 for a fully absorbing wall
    return np.prod(r[None] ** hits[:, :, None], axis=1)                 # 0⁰ = 1: images not hitting it


def emission_directions(images, mics):
    """Unit emission directions (n_img, M, 3) at the real source of the ray from each image to each mic."""
    d = mics[None, :, :] - images["pos"][:, None, :]
    if "M" in images:                     # general images (polyroom): mapped back through the reflections
        d = np.einsum("nji,nmj->nmi", images["M"], d)
        return d / np.linalg.norm(d, axis=2, keepdims=True)
    d = np.where(images["flip"][:, None, :], -d, d)
    return d / np.linalg.norm(d, axis=2, keepdims=True)


def directivity_gain(pattern, axis, directions, floor_db=REAR_FLOOR_DB):
    """Gain ``max(p + (1 − p) cos θ, 10^(floor_db/20))`` of a first-order pattern; θ from ``axis`` (3,) unit."""
    p = PATTERNS[pattern] if isinstance(pattern, str) else float(pattern)
    return np.maximum(p + (1 - p) * directions @ np.asarray(axis, float), 10 ** (floor_db / 20))


def mean_power_gain(pattern, floor_db=REAR_FLOOR_DB):
    """Power gain of :func:`directivity_gain` averaged over all directions (the diffuse-field share):
    p² + (1 − p)²/3 without the floor; integrated numerically over cos θ with it."""
    x = np.linspace(-1.0, 1.0, 20001)
    g = directivity_gain(pattern, np.array([0.0, 0.0, 1.0]), np.stack([0 * x, 0 * x, x], axis=1), floor_db)
    from scipy.integrate import trapezoid  # here: numpy < 2 has no np.trapezoid, scipy.integrate costs ~0.1 s to import

    return float(trapezoid(g ** 2, x) / 2)


# ----------------------------------------------------------------------------------------------- bands, tail
def band_weights(freqs):
    """Crossover weights (7, F) at ``freqs`` Hz: raised-cosine in log-frequency between band centres,
    flat below the first and above the last; they sum to exactly 1 (zero phase)."""
    f = np.maximum(np.asarray(freqs, float), 1e-3)
    c = np.asarray(BAND_CENTERS)
    w = np.zeros((c.size, f.size))
    w[0, f <= c[0]] = 1.0
    w[-1, f >= c[-1]] = 1.0
    for b in range(c.size - 1):
        sel = (f >= c[b]) & (f < c[b + 1])       # a bin exactly on a centre belongs to that band
        x = np.log(f[sel] / c[b]) / np.log(c[b + 1] / c[b])
        w[b, sel] = np.cos(0.5 * np.pi * x) ** 2
        w[b + 1, sel] = np.sin(0.5 * np.pi * x) ** 2
    return w


def tail_envelopes(t, rt60_bands, volume, c, fs, diffuse_gain):
    """Expected late-tail amplitude per band (7, n) at propagation times ``t`` (n,) s since emission.

    Image-source density: 4π(ct)² c dt / V images per dt, each of energy (β^n / ct)², so a unit source
    gives a mean squared RIR of ``4π c / (V fs)`` per sample times the decay 10^(−6 t / RT60)
    (multiplied by the speaker's diffuse-field power gain). A band's tail is white noise times this
    envelope, then band-weighted, so each band decays at its own Sabine rate.
    """
    level = math.sqrt(4 * math.pi * c * diffuse_gain / (volume * fs))
    return level * 10.0 ** (-3.0 * np.asarray(t)[None, :] / np.asarray(rt60_bands)[:, None])


def diffuse_coherence_mix(mics, freqs, c):
    """Mixing matrices (F, M, M): the symmetric square root ``A = Γ(f)^½`` (so ``A Aᵀ = Γ``), with
    Γ_mn = sinc(2 f |r_m − r_n| / c) (spherically diffuse field). The principal root is smooth in f, so
    the mixing filters are short (an eigenvector basis would jump between bins and smear in time)."""
    freqs = np.asarray(freqs, float)
    d = np.linalg.norm(mics[:, None] - mics[None], axis=2)
    # the root is smooth in f: computed on a coarse grid (≤ COHERENCE_GRID Hz apart), interpolated
    coarse = np.linspace(freqs.min(), freqs.max(), max(2, int(np.ptp(freqs) / COHERENCE_GRID) + 2))
    w, v = np.linalg.eigh(np.sinc(2 * coarse[:, None, None] * d[None] / c))
    root = (v * np.sqrt(np.clip(w, 0, None))[:, None, :]) @ np.swapaxes(v, 1, 2)      # (F', M, M)
    flat = root.reshape(len(coarse), -1)
    out = np.stack([np.interp(freqs, coarse, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    return out.reshape(len(freqs), *d.shape)
