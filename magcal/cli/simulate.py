"""``magcal simulate``: write a recording from the physics simulator, with known truth.

Handy to try ``fit`` and ``diagnose`` without hardware, and to see what each effect looks
like. The truth (the calibration that inverts the simulated physics) is written next to the
CSV as ``FILE.truth.json``; ``--json`` prints it as ``magcal.simulate/1``.

``--model M.yaml`` simulates a sensor model (``magcal diagnose REC --model-out M.yaml`` writes
one fitted to a real recording; docs/sensor-model.md): on the simulator's own motion, or with
``--like REC`` on REC's own timing, channels and field directions (recovered through the
model's inverse) — a twin of REC. ``--seed`` draws another one. The effect options (offset,
scale, noise …) describe the sensor when no model is given and cannot be combined with one;
with a model the truth also carries the whole model under ``model``.
"""

from __future__ import annotations

import json

import numpy as np

from ..core.chips import CHIP_NAMES, chip_named
from ..core.errors import ConfigError, InputError
from ..core.series import Series
from ..recordings.atomic import write_text
from ..recordings.table import save_csv
from ..sim.physics import Current, Motion, Physics, Scenario, Temperature
from .common import Progress, document, print_json
from .options import (add, add_alias, existing_file, field_scale_ut, floats, noise_scale_ut, non_negative,
                      non_negative_int, positive, share)

HELP = "write a simulated magnetometer recording (CSV, µT) with known physics, on any supported chip"


def add_arguments(p) -> None:
    add(p, "output", required=True, help="the CSV file to write (t, mx, my, mz in µT, temp_c, current_a)")
    p.add_argument("--seconds", type=positive, default=60.0, metavar="S", help="length of the recording")
    p.add_argument("--rate", type=positive, default=None, metavar="HZ",
                   help="samples per second (default: 50, or the model's rate)")
    p.add_argument("--model", type=existing_file, metavar="M.yaml",
                   help="simulate this sensor model (YAML or JSON, as diagnose --model-out writes it)")
    p.add_argument("--like", type=existing_file, metavar="REC",
                   help="with --model: a twin of REC, on its own times, channels and field directions")
    p.add_argument("--chip", choices=CHIP_NAMES, default="mpu9150",
                   help="the part whose quantum, range and overflow the readings have (default mpu9150)")
    p.add_argument("--bits", type=int, choices=(13, 14, 16), default=None,
                   help="the magnetometer's resolution (mpu9250: 14 or 16, default 16)")
    p.add_argument("--seed", type=non_negative_int, default=1, help="random seed: the same seed gives the same recording")
    p.add_argument("--motion", choices=("sphere", "tilt", "yaw", "still"), default="sphere",
                   help="how the board is turned: every direction (sphere), ±30° tilts, flat turns (yaw), or held still")
    _quantity(p, "--offset-ut", "--offset", default="23.5,-41.2,12.8", type=floats(3), metavar="X,Y,Z",
              help="hard iron, µT")
    _quantity(p, "--scale", None, default="1,1,1", type=floats(3), metavar="X,Y,Z",
              help="axis gains (soft iron, diagonal)")
    _quantity(p, "--noise-ut", "--noise", default=0.4, type=noise_scale_ut, metavar="UT", help="white noise σ per axis, µT")
    _quantity(p, "--field-ut", "--field", default=50.0, type=field_scale_ut, metavar="UT", help="Earth's field strength, µT")
    p.add_argument("--temp-swing", type=non_negative, default=0.0, metavar="C",
                   help="peak-to-peak die temperature swing, °C")
    p.add_argument("--temp-coef", type=floats(3), default="0,0,0", metavar="X,Y,Z", help="offset change per °C, µT/°C")
    p.add_argument("--current", type=non_negative, default=0.0, metavar="A", help="intermittent current level, A")
    p.add_argument("--current-coef", type=floats(3), default="0,0,0", metavar="X,Y,Z",
                   help="offset change per A of current, µT/A")
    p.add_argument("--drift", type=floats(3), default="0,0,0", metavar="X,Y,Z", help="offset drift, µT/s")
    p.add_argument("--glitch-rate", type=share, default=0.0, metavar="P",
                   help="share of samples with a 4–15 µT jump (0 ≤ P < 1)")
    add(p, "json", "quiet")


def _quantity(p, flag: str, old: str | None, **kw) -> None:
    """An option whose old spelling (``--noise``) still works, unlisted."""
    dest = flag.lstrip("-").replace("-", "_")
    p.add_argument(flag, dest=dest, **kw)
    if old:
        add_alias(p, old, dest=dest, type=kw["type"])


_SENSOR = ("offset_ut", "scale", "noise_ut", "field_ut", "temp_coef", "current_coef", "drift", "glitch_rate")
_DEFAULTS = {"offset_ut": (23.5, -41.2, 12.8), "scale": (1.0, 1.0, 1.0), "noise_ut": 0.4, "field_ut": 50.0,
             "temp_coef": (0.0, 0.0, 0.0), "current_coef": (0.0, 0.0, 0.0), "drift": (0.0, 0.0, 0.0),
             "glitch_rate": 0.0}  # the sensor options' defaults (add_arguments): a model replaces them


MAX_SAMPLES = 10_000_000  # 28 h at 100 Hz; the recording is built in memory


def _check(args) -> None:
    """What the options ask for must be a recording that can be made (ConfigError names it)."""
    if args.like and not args.model:
        raise ConfigError("--like needs --model (the sensor to simulate on REC's motion)")
    if args.model:
        given = [k for k in _SENSOR if getattr(args, k) != _DEFAULTS[k]]
        if given:
            raise ConfigError("--model describes the sensor; drop " + ", ".join(
                "--" + k.replace("_", "-") for k in given))
    if min(args.scale) <= 0:
        raise ConfigError(f"--scale: every axis gain must be positive (a gain of 0 or less is no sensor), got "
                          f"{','.join(f'{v:g}' for v in args.scale)}")
    if args.glitch_rate >= 1:
        raise ConfigError(f"--glitch-rate is the share of samples with a jump and must be below 1 (every sample "
                          f"a jump is no reading), got {args.glitch_rate:g}")


def _physics(args) -> Physics:
    return Physics(
        field_ut=args.field_ut,
        hard_iron_ut=args.offset_ut,
        distortion=tuple(tuple(r) for r in np.diag(args.scale)),
        noise_ut=args.noise_ut,
        temp_coef_ut_per_c=args.temp_coef,
        current_coef_ut_per_a=args.current_coef,
        drift_ut_per_s=args.drift,
        glitch_rate=args.glitch_rate,
    )


def _chip(args):
    try:
        return chip_named(getattr(args, "chip", "mpu9150"), getattr(args, "bits", None))
    except ValueError as exc:
        raise ConfigError(f"--chip/--bits: {exc}") from None


def _scenario(args, model=None) -> Scenario:
    return _bare_scenario(args, model).on_chip(_chip(args))


def _bare_scenario(args, model=None) -> Scenario:
    return Scenario(
        physics=_physics(args) if model is None else Physics(field_ut=model.calibration.field_ut),
        motion=Motion(args.motion),
        temperature=Temperature(base_c=25.0, swing_c=args.temp_swing),
        current=Current(level_a=args.current),
        seed=args.seed,
        model=model,
    )


def _like(model, args) -> tuple[Series, dict]:
    """A twin of the recording ``args.like``: its times, channels and field directions."""
    from ..app.load import load_series

    rec = load_series(args.like).only_valid()
    chans = dict(rec.channels)
    chans.setdefault("t_s", rec.t_s)
    missing = [c for c in model.calibration.coef_ut_per_unit if c not in chans]
    if missing:
        raise InputError(f"{args.like} lacks the channel(s) {', '.join(missing)} the model's terms need")
    if len(rec) < 2:
        raise InputError(f"{args.like} has {len(rec)} valid samples; a twin needs at least 2")
    from ..diagnose import twin

    u, draws = twin.twin_draws(model, twin.twin_directions(model, rec), rec.t_s, args.seed)
    m, valid = model.distort(u, chans, draws)
    hit = np.any(draws.glitch_ut != 0, axis=1)
    rows = np.flatnonzero(hit if draws.glitch_along_ut is None else hit | (draws.glitch_along_ut != 0))
    series = Series(t_s=rec.t_s, field_ut=m, channels=dict(rec.channels), valid=valid)
    return series, {"glitch_rows": [int(i) for i in rows], "like": args.like}


def _simulated(args, model) -> tuple[Series, dict]:
    if args.like:
        return _like(model, args)
    rate = args.rate or (model.rate_hz if model else 50.0)
    n = args.seconds * rate
    if n > MAX_SAMPLES:
        raise ConfigError(f"--seconds {args.seconds:g} at {rate:g} Hz is {n:.3g} samples, more than "
                          f"{MAX_SAMPLES:,}; ask for a shorter or slower recording")
    run_ = _scenario(args, model).simulate(int(round(n)), rate)
    return run_.series, {"glitch_rows": [int(i) for i in run_.glitch_idx]}


def run(args) -> int:
    _check(args)
    model = None
    if args.model:
        from ..app.sensor_file import load_model

        model = load_model(args.model)
    with Progress(quiet=args.quiet).working(f"simulate {args.output}") as ticker:
        ticker.doing("a twin of " + args.like if args.like else "simulating")
        series, truth = _simulated(args, model)
        ticker.doing(f"writing {len(series):,} samples".replace(",", " "))
        save_csv(series, args.output)
    cal = model.calibration if model else _physics(args).truth()
    truth = {"truth": cal.to_dict(), **truth, "n_samples": len(series), "output": args.output,
             "chip": _chip(args).label}
    if model:
        truth["model"] = model.to_dict()
    if model and not args.like and model.source.get("clock") is False:
        truth["note"] = (f"the model was learned from a recording without time ({model.source.get('recording')}): "
                         "its rate and its wander's bands count samples, not seconds, and the simulator's "
                         "own motion has no such clock; --like REC draws the twin on the recording's own samples")
    try:
        write_text(args.output + ".truth.json", json.dumps(truth, indent=2))
    except OSError as exc:
        raise InputError(f"{args.output}.truth.json: cannot write: {exc.strerror or exc}") from None
    if args.json:
        print_json(document("simulate", truth))
    else:
        print(f"wrote {len(series)} samples to {args.output}; truth in {args.output}.truth.json")
        if "note" in truth:
            print(f"note: {truth['note']}")
    return 0
