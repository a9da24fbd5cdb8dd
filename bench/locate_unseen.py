"""The locate step judged on effects built differently from bench/locate_eval.py's.

    python bench/locate_unseen.py [--quick] [--sizes 3,7] [--seed N] [--only ramp,hum_mod] [--json out.json]

Issue 40 is to be judged on cases it has never seen, "including effects built differently from
any list the project keeps". locate_eval.py injects one fixed construction per effect, and every
method was tuned on exactly those; this bench keeps its recordings (``base_recordings``: the two
simulated ones and the open raw recordings), its judge (``judge_case``: located, named, specific
false claims; the lines a recording carries set aside) and its summary, and builds each effect
another way, at other sizes (default 3× and 7× the recording's own floor, the RMS radial
residual of a plain ellipsoid), placed by its own ``--seed`` from one generator drawn in order over
the recordings and, within each, the sizes (so ``--sizes``, ``--quick`` and ``--recordings`` move
the placements: a ``--sizes 3`` run's cases are not the 3× cases of ``--sizes 3,7``; ``--only``
does not, every draw is made):

- ``ramp`` (hard_iron_step): a part slid into place — the offset moves along a random vector
  linearly over 0.2–1.5 s, starting at 25–75 % of the span; truth the ramp's middle.
- ``soft_sym`` (soft_iron_change): a part of soft iron attached — from a random time on, the
  field about the centre is multiplied by I + εS, S a random symmetric matrix of spectral norm
  1 (every axis and the couplings between them), ε the size over the recording's radius.
- ``hum_mod`` (narrowband_line): mains hum of 50 or 60 Hz (at random; the other where the
  first aliases to under 20 cycles) aliased by the sample clock, along a random unit direction
  (all three axes), its amplitude modulated ±30 % over one to three slow cycles (the load
  drawing the current changes).
- ``temp_warm`` (temperature_gain): a board warming up, T = T0 + ΔT(1 − e^(−t/τ)), τ a third of
  the take, logged at 1/16 °C; the gain of each axis changes with it by its own coefficient.
- ``lag_pwm`` (lagged_channel): a current of held levels, ramps and PWM-like steps of random
  levels and durations, reaching the sensor through a first-order lag of 0.2–1.5 s.
- ``stuck_const`` (stuck_axis): y or z reads a constant that is not its last value — 0 counts,
  or a rail beyond the field (a sensor that lost its axis) — for 2–8 s.
- ``sign_flip`` (axis_swap): one axis negated for 2–8 s (a driver's orientation switch).
- ``swap_yz`` (axis_swap): y and z read swapped for 2–8 s.
- ``rail_one`` (saturation): one axis clipped on one side only, at its 90–97th percentile (or
  the mirror), the other axes and the other side untouched (a range set too small for that axis
  with an offset).
- ``repeat_t`` (repeated_timestamps): 2–5 % of rows carry the time of the row before (a logger
  stamping a buffered sample with the last time it read).
- ``back_t`` (out_of_order_timestamps): 1–4 % of rows written after the row that follows them
  (packets flushed out of order); the samples themselves are true.

Controls are the recordings as they are (one per recording). The sealed recordings of
docs/sealed.md other than betaflight_apex5_tpu_03 (which locate_eval already shows) count in
the totals under a masked name (``sealed#k``) and are never printed case by case.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from locate_eval import MIN_HUM_CYCLES, Case, _s, base_recordings, floor_ut, judge_case, recording_lines, summarise  # noqa: E402
from model_choice import SEALED  # noqa: E402

from magcal.fit import fit_calibration  # noqa: E402

SHOWN_SEALED = ("betaflight_apex5_tpu_03",)  # locate_eval already shows its per-case rows


def _centre_radius(m: np.ndarray) -> tuple[np.ndarray, float]:
    r = fit_calibration(m, model="sphere")
    b = r.calibration.offset_ut if r else m.mean(0)
    return b, float(np.median(np.linalg.norm(m - b, axis=1)))


def _unit(rng: np.random.Generator) -> np.ndarray:
    d = rng.standard_normal(3)
    return d / np.linalg.norm(d)


def _stretch(t: np.ndarray, rng: np.random.Generator) -> tuple[int, int, list[float]]:
    """A 2–8 s run of rows placed in the middle 20–90 % of the take."""
    n = len(t)
    rate = 1.0 / float(np.median(np.diff(t)))
    length = max(3, int(rng.uniform(2, 8) * rate))
    i0 = int(rng.integers(n // 5, max(n // 5 + 1, int(0.9 * n) - length)))
    i1 = min(i0 + length, n - 1)
    return i0, i1, [float(t[i0]), float(t[i1])]


def ramp(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    span = t[-1] - t[0]
    start = float(t[0] + span * rng.uniform(0.25, 0.75))
    dur = float(rng.uniform(0.2, 1.5))
    shape = np.clip((t - start) / dur, 0.0, 1.0)
    return Case(f"{name}/ramp", "hard_iron_step", _s(t, m + np.outer(shape, amp_ut * _unit(rng))),
                {"time_s": start + dur / 2})


def soft_sym(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    a = rng.standard_normal((3, 3))
    s = (a + a.T) / 2
    s /= np.max(np.abs(np.linalg.eigvalsh(s)))
    tau = float(t[0] + (t[-1] - t[0]) * rng.uniform(0.25, 0.75))
    after = t >= tau
    m2 = m.copy()
    m2[after] = b + (m[after] - b) @ (np.eye(3) + amp_ut / radius_ut * s).T
    return Case(f"{name}/soft_sym", "soft_iron_change", _s(t, m2), {"time_s": tau})


def mains_alias_hz(t: np.ndarray, rng: np.random.Generator) -> float:
    """50 or 60 Hz at random, aliased by the sample clock; the other where the first leaves
    under ``MIN_HUM_CYCLES`` cycles over the span; neither: a line at 0.137 of the rate."""
    rate = 1.0 / float(np.median(np.diff(t)))
    order = (50.0, 60.0) if rng.random() < 0.5 else (60.0, 50.0)
    for mains in order:
        f = abs(mains - rate * round(mains / rate))
        if f * float(t[-1] - t[0]) >= MIN_HUM_CYCLES:
            return f
    return 0.137 * rate


def hum_mod(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    f = mains_alias_hz(t, rng)
    span = float(t[-1] - t[0])
    env = 1.0 + 0.3 * np.sin(2 * np.pi * t / (span / rng.uniform(1.0, 3.0)) + rng.uniform(0, 2 * np.pi))
    wave = amp_ut * np.sqrt(2) * env * np.cos(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return Case(f"{name}/hum_mod", "narrowband_line", _s(t, m + np.outer(wave, _unit(rng))), {"frequency_hz": f})


def temp_warm(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    span = float(t[-1] - t[0])
    t0_c, rise_c = rng.uniform(15, 25), rng.uniform(10, 25)
    temp_c = t0_c + rise_c * (1 - np.exp(-(t - t[0]) / (span / 3)))
    per_axis = rng.uniform(0.3, 1.7, 3) * amp_ut / radius_ut / rise_c  # gain change per °C, each axis
    m2 = b + (1 + np.outer(temp_c - t0_c, per_axis)) * (m - b)
    logged = np.round((temp_c + 0.03 * rng.standard_normal(len(t))) * 16) / 16
    return Case(f"{name}/temp_warm", "temperature_gain", _s(t, m2, {"temp_c": logged}), {"channel": "temp_c"})


def pwm_current(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Held levels, ramps between levels and PWM-like bursts, each 0.5–5 s, levels 0–10 A."""
    cur = np.zeros(len(t))
    at, level = float(t[0]), rng.uniform(0, 10)
    while at < t[-1]:
        dur, nxt = rng.uniform(0.5, 5.0), rng.uniform(0, 10)
        sel = (t >= at) & (t < at + dur)
        kind = rng.integers(3)
        if kind == 0:
            cur[sel] = nxt
        elif kind == 1:
            cur[sel] = level + (nxt - level) * (t[sel] - at) / dur
        else:
            period = rng.uniform(0.3, 1.2)
            cur[sel] = np.where(((t[sel] - at) / period) % 1.0 < rng.uniform(0.2, 0.8), nxt, level)
        at, level = at + dur, nxt
    return cur


def lag_pwm(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    cur = pwm_current(t, rng)
    tau_s = float(rng.uniform(0.2, 1.5))
    dt = np.diff(t, prepend=t[0])
    lagged = np.empty_like(cur)
    lagged[0] = cur[0]
    for i in range(1, len(t)):
        a = np.exp(-dt[i] / tau_s)
        lagged[i] = a * lagged[i - 1] + (1 - a) * cur[i]
    beta = amp_ut / max(float(np.ptp(lagged)), 1e-9) * _unit(rng)
    logged = cur + 0.1 * rng.standard_normal(len(t))
    return Case(f"{name}/lag_pwm", "lagged_channel", _s(t, m + np.outer(lagged, beta), {"current_a": logged}),
                {"channel": "current_a", "lag_s": tau_s, "coef_ut_per_unit": beta})


def stuck_const(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    i0, i1, stretch = _stretch(t, rng)
    axis = int(rng.integers(1, 3))
    rail = float(np.round(1.5 * np.max(np.abs(m)))) * (1 if rng.random() < 0.5 else -1)
    m2 = m.copy()
    m2[i0:i1, axis] = 0.0 if rng.random() < 0.5 else rail
    return Case(f"{name}/stuck_const", "stuck_axis", _s(t, m2), {"time_s": stretch, "axis": "xyz"[axis]})


def sign_flip(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    i0, i1, stretch = _stretch(t, rng)
    m2 = m.copy()
    m2[i0:i1, int(rng.integers(3))] *= -1.0
    return Case(f"{name}/sign_flip", "axis_swap", _s(t, m2), {"time_s": stretch})


def swap_yz(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    i0, i1, stretch = _stretch(t, rng)
    m2 = m.copy()
    m2[i0:i1, [1, 2]] = m[i0:i1, [2, 1]]
    return Case(f"{name}/swap_yz", "axis_swap", _s(t, m2), {"time_s": stretch})


def rail_one(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    axis = int(rng.integers(3))
    m2 = m.copy()
    if rng.random() < 0.5:
        m2[:, axis] = np.minimum(m[:, axis], np.percentile(m[:, axis], rng.uniform(90, 97)))
    else:
        m2[:, axis] = np.maximum(m[:, axis], np.percentile(m[:, axis], rng.uniform(3, 10)))
    return Case(f"{name}/rail_one", "saturation", _s(t, m2), {"axis": "xyz"[axis]})


def _rows(t: np.ndarray, rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    n = len(t)
    k = max(2, int(rng.uniform(lo, hi) * n))
    return np.unique(rng.choice(np.arange(2, n - 2), size=k, replace=False))


def repeat_t(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    rows = _rows(t, rng, 0.02, 0.05)
    rows = rows[np.diff(rows, prepend=-2) > 1]  # no two in a row: each repeats a true time
    t2 = t.copy()
    t2[rows] = t[rows - 1]
    return Case(f"{name}/repeat_t", "repeated_timestamps", _s(t2, m), {"time_s": [float(x) for x in t[rows]]})


def back_t(name, t, m, rng, amp_ut, b, radius_ut) -> Case:
    rows = _rows(t, rng, 0.01, 0.04)
    rows = rows[np.diff(rows, prepend=-3) > 2]  # pairs apart
    order = np.arange(len(t))
    order[rows], order[rows + 1] = rows + 1, rows
    return Case(f"{name}/back_t", "out_of_order_timestamps", _s(t[order], m[order]),
                {"time_s": [float(x) for x in t[rows]]})


CONSTRUCTIONS = (ramp, soft_sym, hum_mod, temp_warm, lag_pwm, stuck_const, sign_flip, swap_yz, rail_one,
                 repeat_t, back_t)


def inject(name, t, m, rng, size: float, only: tuple[str, ...] = ()) -> list[Case]:
    """One case per construction at ``size`` × the recording's floor (every draw is made, so the
    placements do not depend on ``only``)."""
    amp_ut = size * floor_ut(m)
    b, radius_ut = _centre_radius(m)
    cases = [build(name, t, m, rng, amp_ut, b, radius_ut) for build in CONSTRUCTIONS]
    return [c for c in cases if not only or c.name.split("/")[1] in only]


def shown_name(name: str, sealed_seen: dict) -> str:
    """The name a recording is printed under: sealed ones (but the one locate_eval shows) masked."""
    if name in SEALED and name not in SHOWN_SEALED:
        return sealed_seen.setdefault(name, f"sealed#{len(sealed_seen) + 1}")
    return name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="four real recordings (and the two simulated)")
    ap.add_argument("--sizes", default="3,7", help="effect sizes, × the recording's floor (default 3,7)")
    ap.add_argument("--seed", type=int, default=7070, help="placements of the effects (default 7070)")
    ap.add_argument("--only", default="", help="only these constructions, e.g. ramp,hum_mod (default: all)")
    ap.add_argument("--recordings", default="", help="only recordings whose name holds one of these (comma list)")
    ap.add_argument("--json", help="write every (printable) case's verdict here")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    only = tuple(x for x in args.only.split(",") if x)
    pick = tuple(x for x in args.recordings.split(",") if x)
    rows, sealed_seen = [], {}
    for name, (t, m) in base_recordings(args.quick).items():
        if pick and not any(p in name for p in pick):
            continue
        shown = shown_name(name, sealed_seen)
        rows.append(judge_case(Case(f"{shown}/control", "", _s(t, m)), recording_lines(name, t, m)))
        for size in (float(x) for x in args.sizes.split(",")):
            for case in inject(shown, t, m, rng, size, only):
                r = judge_case(case, recording_lines(name, t, m)) | {"size": size}
                rows.append(r)
                if not shown.startswith("sealed#"):
                    print(f"{r['case']:44s} x{size:<4} named {r['named']!s:5} located {r['located']!s:5} "
                          f"said {r['said']} false {r['false_claims']}", flush=True)
    summarise(rows)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump([r for r in rows if not r["case"].startswith("sealed#")], fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
