"""`calib simulate -o OUT_DIR`: a simulated recording session (docs/formats.md section 1) + truth/ (section 4)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Optional

import typer

from calib.pipeline.formats import validate as V
from calib.pipeline.formats.io import InputError
from calib.pipeline.formats.outputs import owned_output
from calib.pipeline.simulate.presets import PRESETS
from .common import console, progress_display, user_errors, waiting
from .signals import checked


def _out_dir(positional, option):
    """The output folder from -o (or, deprecated, the positional argument)."""
    if positional is not None and option is not None:
        raise InputError("give the output folder once: -o OUT_DIR")
    if positional is None and option is None:
        raise InputError("missing the output folder: -o OUT_DIR")
    return positional if positional is not None else option


@user_errors
def simulate(
    out_pos: Optional[Path] = typer.Argument(None, metavar="OUT_DIR", show_default=False,
                                             help="deprecated: use -o OUT_DIR"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", show_default=False,
                                       help="session folder to write (session.toml, <array>.wav, events.csv, truth/)"),
    preset: Optional[str] = typer.Option(None, help=f"scene preset: {', '.join(PRESETS)} [default: paper-traj3]"),
    seed: Optional[int] = typer.Option(None, help="random seed: same seed, same bytes [default: 0]"),
    scenario: Optional[Path] = typer.Option(None, "--scenario", help="TOML file of scenario keys (options below win)"),
    rt60: Optional[float] = typer.Option(None, help="reverberation time RT60, s (0 = anechoic) [default: 0.3]"),
    snr: Optional[float] = typer.Option(None, help="sensor SNR re. the mean direct-path chirp power, dB "
                                                   "('inf' = noise-free) [default: 30]"),
    diffuse_snr: Optional[float] = typer.Option(None, help="diffuse pink-noise SNR (diffuse-field coherence), dB "
                                                           "[default: inf = off]"),
    fs: Optional[int] = typer.Option(None, help="sampling rate of every recorder, Hz [default: 16000]"),
    n_arrays: Optional[int] = typer.Option(None, help="number of arrays [default: 5, lab3: 3]"),
    n_events: Optional[int] = typer.Option(None, help="use the first N speaker stops of the preset [default: all]"),
    interval: Optional[float] = typer.Option(None, help="mean time between chirps, s (±25 % jitter) [default: 2]"),
    chirp_duration: Optional[float] = typer.Option(None, help="chirp length, s [default: 0.5]"),
    interferers: Optional[int] = typer.Option(None, help="number of random interfering noise bursts [default: 0]"),
    sigma_odo: Optional[float] = typer.Option(None, help="odometry noise per step and axis, m [default: 0.01]"),
    subtype: Optional[str] = typer.Option(None, help="WAV sample format: FLOAT, PCM_24 or PCM_16 [default: FLOAT]"),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="any scenario key: KEY=VALUE (TOML value; "
                                             "dotted keys for tables, e.g. chirp.kind=exponential); repeatable"),
    clock: Optional[list[str]] = typer.Option(None, "--clock", help="a faulty clock: ARRAY=PRESET (drop, insert, "
                                              "esp, warmup, walk, rate44k, rate1pct, rate1000ppm) or ARRAY={TOML "
                                              "table}, e.g. 'A3={steps=[{size=-0.02, time=60}]}'; repeatable"),
    force: bool = typer.Option(False, "--force", help="replace OUT_DIR if it exists and is not empty"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar or summary"),
):
    """Simulate a room with asynchronous microphone arrays and a chirping speaker; write a session (-o OUT_DIR)."""
    out_dir = _out_dir(out_pos, out)
    _check_options(rt60=rt60, snr=snr, diffuse_snr=diffuse_snr, fs=fs, n_arrays=n_arrays, n_events=n_events,
                   interval=interval, chirp_duration=chirp_duration, interferers=interferers, sigma_odo=sigma_odo,
                   seed=seed)
    over: dict[str, Any] = {k: v for k, v in {
        "preset": preset, "seed": seed, "rt60": rt60, "snr": snr, "diffuse_snr": diffuse_snr, "fs": fs,
        "n_arrays": n_arrays, "n_events": n_events, "interval": interval, "n_interferers": interferers,
        "sigma_odo": sigma_odo, "subtype": subtype}.items() if v is not None}
    if chirp_duration is not None:
        over["chirp"] = {"duration": chirp_duration}
    for item in set_ or []:
        _set(over, item)
    for item in clock or []:
        _clock(over, item)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())) and not force:
        raise InputError(f"{out_dir}: exists and is not empty (use --force to replace it)")
    # the simulator is loaded here: it needs scipy.spatial and more, which every other command would pay at start
    from calib.pipeline.simulate.roomsim import load_scenario, make_scenario, validate_scenario

    if scenario is not None:
        sc = load_scenario(scenario, **over)
    else:
        sc = make_scenario(over.pop("preset", "paper-traj3"), over.pop("seed", 0), **over)
        validate_scenario(sc)
    with owned_output([out_dir], [scenario], command="calib simulate", on_wait=waiting):
        if quiet:
            path = _run(sc, out_dir, checked())
        else:
            path = _simulate_with_bar(sc, out_dir)
    if out_pos is not None:  # after success only: a bad input stays one line
        print("note: `calib simulate OUT_DIR` is deprecated; use `calib simulate -o OUT_DIR`", file=sys.stderr)
    if not quiet:
        console.print(_summary(sc) + f" → {path}")


def _summary(sc):
    """One line: the scene's arrays, chirps, acoustics and deployment conditions."""
    t = sc["t_emit"]
    rates = sorted({int(a.get("fs", sc["fs"])) for a in sc["arrays"]})
    fs = f"{rates[0]}" if len(rates) == 1 else f"{rates[0]}–{rates[-1]}"
    n_obs = len(sc.get("obstacles") or [])
    extra = [x for x, on in (("non-convex room", sc.get("floor_plan") is not None),
                             (f"{n_obs} obstacle{'s' * (n_obs != 1)}", n_obs > 0),
                             ("speaker moving while chirping", sc.get("trajectory") is not None)) if on]
    return (f"{sc['preset']} (seed {sc['seed']}): {len(sc['arrays'])} arrays, {len(t)} chirps over "
            f"{t[-1] - t[0]:.1f} s, RT60 {sc['rt60']:g} s, SNR {sc['snr']:g} dB, fs {fs} Hz"
            + "".join(f", {x}" for x in extra))


# ranges of the numeric options (docs/reliability.md): (lo, hi, lo open, integer)
SIM_OPTION_RANGES = {
    "rt60": (0.0, 10.0, False, False), "snr": (-60.0, 300.0, False, False),
    "diffuse_snr": (-60.0, 300.0, False, False), "fs": (*V.SAMPLE_RATE, False, True),
    "n_arrays": (1, 64, False, True), "n_events": (0, V.MAX_EVENTS, False, True),
    "interval": (0.0, 3600.0, True, False), "chirp_duration": (*V.CHIRP_DURATION, False, False),
    "interferers": (0, 1000, False, True), "sigma_odo": (0.0, 100.0, False, False), "seed": (0, 2**32 - 1, False, True),
}
NO_NOISE = ("snr", "diffuse_snr")  # 'inf' switches this noise off


def _check_options(**values):
    """InputError unless every given numeric option is finite (or inf where documented) and in range."""
    for name, v in values.items():
        if v is None or (name in NO_NOISE and v == float("inf")):
            continue
        lo, hi, lo_open, integer = SIM_OPTION_RANGES[name]
        V.option(v, name.replace("_", "-"), lo=lo, hi=hi, lo_open=lo_open, integer=integer)


def _simulate_with_bar(sc, out_dir):
    """The simulation with progress (a bar on a terminal, timestamped lines in a log file)."""
    with progress_display("simulate") as progress:
        return _run(sc, out_dir, checked(progress))


def _run(sc, out_dir, progress):
    """The simulation of scenario ``sc`` into ``out_dir`` (the simulator loaded only now)."""
    from calib.pipeline.simulate.roomsim import simulate as run_simulation

    return run_simulation(sc, out_dir, progress=progress, overwrite=True)


def _set(over, item):
    """Apply one ``--set KEY=VALUE`` to the overrides (VALUE read as TOML, else as a string)."""
    from calib.tomlcompat import tomllib

    key, sep, text = item.partition("=")
    key = key.strip()
    if not sep or not key or any(not k for k in key.split(".")):
        raise InputError(f"--set {item!r}: expected KEY=VALUE")
    try:
        value = tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    *path, last = key.split(".")
    node = over
    for k in path:
        node = node.setdefault(k, {})
        if not isinstance(node, dict):
            raise InputError(f"--set {item!r}: {k!r} is not a table")
    node[last] = value


def _clock(over, item):
    """Apply one ``--clock ARRAY=FAULT`` (a preset name of ``pipeline.simulate.clocks`` or a TOML table)."""
    name, sep, text = item.partition("=")
    if not sep or not name.strip() or not text.strip():
        raise InputError(f"--clock {item!r}: expected ARRAY=PRESET or ARRAY={{TOML table}}")
    from calib.pipeline.simulate.clocks import CLOCK_PRESETS

    text = text.strip()
    if text.startswith("{"):
        from calib.tomlcompat import tomllib

        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"--clock {item!r}: not a TOML table ({exc})") from None
    elif text in CLOCK_PRESETS:
        value = text
    else:
        raise InputError(f"--clock {item!r}: unknown clock preset {text!r} (known: {', '.join(CLOCK_PRESETS)})")
    over.setdefault("clock_faults", {})[name.strip()] = value
