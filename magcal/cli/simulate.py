"""``magcal simulate``: write a recording from the physics simulator, with known truth.

Handy to try ``fit`` and ``diagnose`` without hardware, and to see what each effect looks
like. The truth (the calibration that inverts the simulated physics) is printed, or written
next to the CSV as ``FILE.truth.json``.
"""

from __future__ import annotations

import json

import numpy as np

from ..core.errors import InputError
from ..recordings.table import save_csv
from ..sim.physics import Current, Motion, Physics, Scenario, Temperature
from .common import add_json_option, print_json

HELP = "write a simulated MPU-9150 recording (CSV, µT) with known physics"


def _triple(text: str, what: str) -> tuple:
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"{what} takes three comma-separated numbers, got {text!r}") from None
    if len(v) != 3:
        raise InputError(f"{what} takes three comma-separated numbers, got {text!r}")
    return v


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", required=True, metavar="FILE.csv")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--rate", type=float, default=50.0, metavar="HZ")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--motion", choices=("sphere", "tilt", "yaw", "still"), default="sphere")
    p.add_argument("--offset", default="23.5,-41.2,12.8", metavar="X,Y,Z", help="hard iron, µT")
    p.add_argument("--scale", default="1,1,1", metavar="X,Y,Z", help="axis gains (soft iron, diagonal)")
    p.add_argument("--noise", type=float, default=0.4, metavar="UT")
    p.add_argument("--field", type=float, default=50.0, metavar="UT")
    p.add_argument("--temp-swing", type=float, default=0.0, metavar="C", help="peak-to-peak die temperature swing")
    p.add_argument("--temp-coef", default="0,0,0", metavar="X,Y,Z", help="µT per °C")
    p.add_argument("--current", type=float, default=0.0, metavar="A", help="intermittent current level")
    p.add_argument("--current-coef", default="0,0,0", metavar="X,Y,Z", help="µT per A")
    p.add_argument("--drift", default="0,0,0", metavar="X,Y,Z", help="µT per s")
    p.add_argument("--glitch-rate", type=float, default=0.0, help="share of samples with a 4–15 µT jump")
    add_json_option(p)


def run(args) -> int:
    if args.seconds <= 0 or args.rate <= 0:
        raise InputError("--seconds and --rate must be positive")
    physics = Physics(
        field_ut=args.field,
        hard_iron_ut=_triple(args.offset, "--offset"),
        distortion=tuple(tuple(r) for r in np.diag(_triple(args.scale, "--scale"))),
        noise_ut=args.noise,
        temp_coef_ut_per_c=_triple(args.temp_coef, "--temp-coef"),
        current_coef_ut_per_a=_triple(args.current_coef, "--current-coef"),
        drift_ut_per_s=_triple(args.drift, "--drift"),
        glitch_rate=args.glitch_rate,
    )
    sc = Scenario(
        physics=physics,
        motion=Motion(args.motion),
        temperature=Temperature(base_c=25.0, swing_c=args.temp_swing),
        current=Current(level_a=args.current),
        seed=args.seed,
    )
    run_ = sc.simulate(int(round(args.seconds * args.rate)), args.rate)
    save_csv(run_.series, args.output)
    truth = {"truth": run_.truth.to_dict(), "glitch_rows": [int(i) for i in run_.glitch_idx],
             "samples": len(run_.series), "output": args.output}
    with open(args.output + ".truth.json", "w", encoding="utf-8") as f:
        json.dump(truth, f, indent=2)
    if args.json:
        print_json(truth)
    else:
        print(f"wrote {len(run_.series)} samples to {args.output}; truth in {args.output}.truth.json")
    return 0
