"""The ODAS export: one complete ``odaslive`` configuration per array (libconfig syntax; ODAS reads one array per
process), its ``mics`` and spatial filter from the calibration.

``mu`` = R·m (m): array-centred, axes of the reference array's frame, so ODAS's directions come out in that
frame; ``sigma2`` the mic position's covariance (m²) from the calibrated rotation's; ``direction`` the array's
z axis (also the spatial filter's: ODAS then searches the half-space the mics face). The other sections are
ODAS's usual values; ``raw`` (rate, bits, channels, sound card) and ``mapping`` are the user's to set.
"""
from __future__ import annotations

import numpy as np

from calib.pipeline.formats.results import Calibration

ANGLE_DEG = (80.0, 90.0)  # ODAS's pick-up cone (deg off the array's z axis): full gain to 80°, none beyond 90°
SAMPLE_RATE = 16000       # Hz: the raw section's rate (set it to the recorder's)
HOP, FRAME = 128, 256     # samples: ODAS's STFT hop and frame


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _f(v):
    """A float in libconfig syntax that reads back as the same double (repr: shortest round trip, with . or e)."""
    return repr(float(v))


def _vec(values):
    return "( " + ", ".join(_f(v) for v in values) + " )"


def mic_blocks(cal: Calibration):
    """{array: [(mu (3,), sigma2 (3, 3), direction (3,)), ...]} (see the module docstring)."""
    labels = [] if cal.covariance is None else list(cal.covariance.index)
    out = {}
    for a in cal.arrays:
        R = a.rotation.as_matrix()
        rot_lab = [f"{a.name}.r{c}" for c in "xyz"]
        if cal.covariance is not None and all(lab in labels for lab in rot_lab):
            S_phi = cal.covariance.loc[rot_lab, rot_lab].to_numpy(float)
        else:
            S_phi = np.zeros((3, 3))  # the reference array: its rotation is the frame, known exactly
        rows = []
        for m in a.mics:
            J = -R @ _skew(m)  # d(R Exp(φ) m)/dφ at φ = 0
            rows.append((R @ m, J @ S_phi @ J.T, R[:, 2]))
        out[a.name] = rows
    return out


def _mics(rows):
    items = []
    for k, (mu, s2, d) in enumerate(rows):
        items.append(f"        # microphone {k + 1} (WAV channel {k} of the session's mics)\n"
                     f"        {{ mu = {_vec(mu)};\n          sigma2 = {_vec(s2.ravel())};\n"
                     f"          direction = {_vec(d)}; angle = {_vec(ANGLE_DEG)}; }}")
    return ",\n".join(items)


# ODAS's processing sections with its usual values (noise estimation, localisation, tracking, separation,
# classification); outputs go to the terminal or nowhere: point them where you need them.
_PROCESSING = """sne: { b = 3; alphaS = 0.1; L = 150; delta = 3.0; alphaD = 0.1; };

ssl: {
    nPots = 4; nMatches = 10; probMin = 0.5; nRefinedLevels = 1; interpRate = 4;
    scans = ( { level = 2; delta = -1; }, { level = 4; delta = -1; } );
    potential: { format = "json"; interface: { type = "terminal"; }; };
};

sst: {
    mode = "kalman"; add = "dynamic";
    active = ( { weight = 1.0; mu = 0.4; sigma2 = 0.0025; } );
    inactive = ( { weight = 1.0; mu = 0.25; sigma2 = 0.0025; } );
    sigmaR2_prob = 0.0025; sigmaR2_active = 0.0225; sigmaR2_target = 0.0025;
    Pfalse = 0.1; Pnew = 0.1; Ptrack = 0.8;
    theta_new = 0.9; N_prob = 5; theta_prob = 0.8; N_inactive = ( 150, 200, 250, 250 ); theta_inactive = 0.9;
    kalman: { sigmaQ = 0.001; };
    particle: { nParticles = 1000; st_alpha = 2.0; st_beta = 0.04; st_ratio = 0.5; ve_alpha = 0.05; ve_beta = 0.2;
                ve_ratio = 0.3; ac_alpha = 0.5; ac_beta = 0.2; ac_ratio = 0.2; Nmin = 0.7; };
    target = ();
    tracked: { format = "json"; interface: { type = "terminal"; }; };
};

sss: {
    mode_sep = "dds"; mode_pf = "ms"; gain_sep = 1.0; gain_pf = 10.0;
    dds: { }; dgss: { mu = 0.01; lambda = 0.5; }; dmvdr: { };
    ms: { alphaPmin = 0.07; eta = 0.5; alphaZ = 0.8; thetaWin = 0.3; alphaWin = 0.3; maxAbsenceProb = 0.9;
          Gmin = 0.01; winSizeLocal = 3; winSizeGlobal = 23; winSizeFrame = 256; };
    ss: { Gmin = 0.01; Gmid = 0.9; Gslope = 10.0; };
    separated: { fS = %(fs)d; hopSize = %(hop)d; nBits = 16; interface: { type = "blackhole"; }; };
    postfiltered: { fS = %(fs)d; hopSize = %(hop)d; nBits = 16; gain = 10.0; interface: { type = "blackhole"; }; };
};

classify: {
    frameSize = 1024; winSize = 3; tauMin = 32; tauMax = 200; deltaTauMax = 7; alpha = 0.3; gamma = 0.05;
    phiMin = 0.15; r0 = 0.2;
    category: { format = "undefined"; interface: { type = "blackhole"; }; };
};
"""


def config(cal: Calibration, name, rows):
    """The text of array ``name``'s configuration (``rows``: its :func:`mic_blocks` entry)."""
    n = len(rows)
    head = (f"# ODAS configuration of array {name}, from calib (calibration.json). mics: mu = R·m (m), array-centred,\n"
            f"# axes of the reference array's frame ({cal.reference_array}): ODAS's directions are in that frame.\n"
            "# Set raw (rate, bits, channels, sound card) and mapping (the card's channel of each mic, from 1).\n")
    body = f"""version = "2.1";

raw: {{
    fS = {SAMPLE_RATE}; hopSize = {HOP}; nBits = 16; nChannels = {n};
    interface: {{ type = "soundcard"; card = 1; device = 0; }};
}};

mapping: {{ map = ( {", ".join(str(k + 1) for k in range(n))} ); }};

general: {{
    epsilon = 1E-20;
    size: {{ hopSize = {HOP}; frameSize = {FRAME}; }};
    samplerate: {{ mu = {SAMPLE_RATE}; sigma2 = 0.01; }};
    speedofsound: {{ mu = {_f(cal.speed_of_sound)}; sigma2 = 25.0; }};
    mics = (
{_mics(rows)}
    );
    spatialfilters = ( {{ direction = {_vec(rows[0][2])}; angle = {_vec(ANGLE_DEG)}; }} );
    nThetas = 181;
    gainMin = 0.25;
}};

"""
    return head + body + _PROCESSING % {"fs": SAMPLE_RATE, "hop": HOP}


def to_odas_configs(cal: Calibration):
    """{array name: the text of its complete ODAS configuration}."""
    return {name: config(cal, name, rows) for name, rows in mic_blocks(cal).items()}
