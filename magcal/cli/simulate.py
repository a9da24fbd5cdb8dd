"""``magcal simulate``: write a recording from the physics simulator, with known truth.

Handy to try ``fit`` and ``diagnose`` without hardware, and to see what each effect looks
like. The truth (the calibration that inverts the simulated physics) is written next to the
CSV as ``FILE.truth.json``; ``--json`` prints it as ``magcal.simulate/1``.
"""

from __future__ import annotations

import json

import numpy as np

from ..recordings.table import save_csv
from ..sim.physics import Current, Motion, Physics, Scenario, Temperature
from .common import Progress, document, print_json
from .options import add, add_alias, floats, non_negative, positive, share

HELP = "write a simulated MPU-9150 recording (CSV, µT) with known physics"


def add_arguments(p) -> None:
    add(p, "output", required=True, help="the CSV file to write (t, mx, my, mz in µT, temp_c, current_a)")
    p.add_argument("--seconds", type=positive, default=60.0, metavar="S", help="length of the recording")
    p.add_argument("--rate", type=positive, default=50.0, metavar="HZ", help="samples per second")
    p.add_argument("--seed", type=int, default=1, help="random seed: the same seed gives the same recording")
    p.add_argument("--motion", choices=("sphere", "tilt", "yaw", "still"), default="sphere",
                   help="how the board is turned: every direction (sphere), ±30° tilts, flat turns (yaw), or held still")
    _quantity(p, "--offset-ut", "--offset", default="23.5,-41.2,12.8", type=floats(3), metavar="X,Y,Z",
              help="hard iron, µT")
    _quantity(p, "--scale", None, default="1,1,1", type=floats(3), metavar="X,Y,Z",
              help="axis gains (soft iron, diagonal)")
    _quantity(p, "--noise-ut", "--noise", default=0.4, type=non_negative, metavar="UT", help="white noise σ per axis, µT")
    _quantity(p, "--field-ut", "--field", default=50.0, type=positive, metavar="UT", help="Earth's field strength, µT")
    p.add_argument("--temp-swing", type=non_negative, default=0.0, metavar="C",
                   help="peak-to-peak die temperature swing, °C")
    p.add_argument("--temp-coef", type=floats(3), default="0,0,0", metavar="X,Y,Z", help="offset change per °C, µT/°C")
    p.add_argument("--current", type=non_negative, default=0.0, metavar="A", help="intermittent current level, A")
    p.add_argument("--current-coef", type=floats(3), default="0,0,0", metavar="X,Y,Z",
                   help="offset change per A of current, µT/A")
    p.add_argument("--drift", type=floats(3), default="0,0,0", metavar="X,Y,Z", help="offset drift, µT/s")
    p.add_argument("--glitch-rate", type=share, default=0.0, metavar="P",
                   help="share of samples with a 4–15 µT jump (0…1)")
    add(p, "json", "quiet")


def _quantity(p, flag: str, old: str | None, **kw) -> None:
    """An option whose old spelling (``--noise``) still works, unlisted."""
    dest = flag.lstrip("-").replace("-", "_")
    p.add_argument(flag, dest=dest, **kw)
    if old:
        add_alias(p, old, dest=dest, type=kw["type"])


def run(args) -> int:
    physics = Physics(
        field_ut=args.field_ut,
        hard_iron_ut=args.offset_ut,
        distortion=tuple(tuple(r) for r in np.diag(args.scale)),
        noise_ut=args.noise_ut,
        temp_coef_ut_per_c=args.temp_coef,
        current_coef_ut_per_a=args.current_coef,
        drift_ut_per_s=args.drift,
        glitch_rate=args.glitch_rate,
    )
    sc = Scenario(
        physics=physics,
        motion=Motion(args.motion),
        temperature=Temperature(base_c=25.0, swing_c=args.temp_swing),
        current=Current(level_a=args.current),
        seed=args.seed,
    )
    n = int(round(args.seconds * args.rate))
    with Progress(quiet=args.quiet).working(f"simulate {args.output}") as ticker:
        ticker.doing(f"{n:,} samples".replace(",", " "))
        run_ = sc.simulate(n, args.rate)
        ticker.doing(f"writing {n:,} samples".replace(",", " "))
        save_csv(run_.series, args.output)
    truth = {"truth": run_.truth.to_dict(), "glitch_rows": [int(i) for i in run_.glitch_idx],
             "n_samples": len(run_.series), "output": args.output}
    with open(args.output + ".truth.json", "w", encoding="utf-8") as f:
        json.dump(truth, f, indent=2)
    if args.json:
        print_json(document("simulate", truth))
    else:
        print(f"wrote {len(run_.series)} samples to {args.output}; truth in {args.output}.truth.json")
    return 0
