"""Are the narrowband lines `diagnose` reports on the two Betaflight "apex5" recordings in the raw
recordings themselves? An answer that uses none of magcal's own code.

    python bench/apex5_lines.py

For both apex5 sessions (and, as a reference, the two logs of the other Betaflight quad in the
same folder) it prints, from the raw CSV of ../shared/data/real/qmc5883l_betaflight_pichim:
the logged motor outputs and throttle (whether anything spun), the spacing of the sample times
and its own spectrum, a Welch spectrum (scipy.signal) of each raw axis, of |m| and of gyro and
accelerometer, for each half of each session, and a Lomb–Scargle periodogram on the raw sample
times (no resampling), each as peaks standing ≥ ``RATIO_MIN`` × the local spectral level (the
median of the spectrum within ±``LOCAL_HZ``). Sample times that are not uniform (spacing away
from its median by more than 1 %) are put on a uniform grid by linear interpolation at the
recording's mean rate (as many samples as it has).

``carried_lines`` is the same pair of spectra as a function: the lines a recording carries before
anything is injected into it, used by bench/locate_eval.py so that a claim of such a line is
counted neither false nor as locating an injected effect.
"""

from __future__ import annotations

import os
import sys

import numpy as np
from scipy import signal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import real_recordings  # noqa: E402

FOLDER = "qmc5883l_betaflight_pichim"
SESSIONS = ("20231014_apex5_mag_on_tpu_02", "20231014_apex5_mag_on_tpu_03")
REFERENCE = ("CalCareful_2282320", "calTest1_198_253_-9")
FC_CENTRE_COUNTS = (958.0, 420.0, 506.0)  # the FC's own hard-iron result (PROVENANCE.md), for |m|
RATIO_MIN = 10.0
LOCAL_HZ = 5.0
MIN_LINE_HZ = 5.0  # below this the hand's motion fills the spectrum
NPERSEG = 1024


def load(stem: str) -> dict[str, np.ndarray]:
    path = real_recordings.root() / FOLDER / f"{stem}_calwindow_mag.csv"
    with open(path) as fh:
        names = fh.readline().strip().split(",")
    a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {k: a[:, i] for i, k in enumerate(names)}


def on_uniform_grid(t: np.ndarray, v: np.ndarray) -> tuple[float, np.ndarray, bool]:
    """(rate, values on a uniform grid, whether they had to be interpolated)."""
    dt = np.diff(t)
    rate = (len(t) - 1) / float(t[-1] - t[0])
    if np.max(np.abs(dt - np.median(dt))) <= 0.01 * np.median(dt):
        return rate, v, False
    grid = t[0] + np.arange(len(t)) / rate
    return rate, np.interp(grid, t, v), True


def spectral_lines(rate: float, v: np.ndarray, ratio_min: float = RATIO_MIN) -> list[tuple[float, float]]:
    """(frequency_hz, × local level) of each Welch peak above ``ratio_min``, strongest first."""
    f, p = signal.welch(v, fs=rate, nperseg=min(NPERSEG, len(v) // 4), detrend="linear")
    return _peaks(f, p, ratio_min)


def _peaks(f, p, ratio_min) -> list[tuple[float, float]]:
    w = max(1, int(round(LOCAL_HZ / (f[1] - f[0]))))
    level = np.array([np.median(p[max(0, i - w) : i + w + 1]) for i in range(len(p))])
    ratio = np.where(f >= MIN_LINE_HZ, p / np.maximum(level, np.finfo(float).tiny), 0.0)
    idx, _ = signal.find_peaks(ratio, height=ratio_min, distance=3)
    return [(float(f[i]), float(ratio[i])) for i in idx[np.argsort(-ratio[idx])]]


def carried_lines(t: np.ndarray, field: np.ndarray) -> list[float]:
    """Frequencies (Hz) of the lines any axis of an un-injected recording carries: the Welch
    peaks on the uniform grid and the Lomb–Scargle peaks on the raw times (30 s at its finer
    resolution separates weak lines, e.g. 11.4 Hz beside 12.25 Hz, that Welch's 0.16 Hz bins merge)."""
    out: list[float] = []
    for k in range(field.shape[1]):
        rate, v, _ = on_uniform_grid(t, field[:, k])
        out.extend(fr for fr, _ in spectral_lines(rate, v) + lomb_scargle_lines(t, field[:, k]))
    return sorted(set(round(f, 2) for f in out))


def lomb_scargle_lines(t: np.ndarray, v: np.ndarray) -> list[tuple[float, float]]:
    """Peaks of a Lomb–Scargle periodogram on the raw times, after the hand's motion is taken
    out with a 31-sample cubic Savitzky–Golay smooth."""
    x = v - signal.savgol_filter(v, 31, 3)
    nyq = 0.5 * (len(t) - 1) / float(t[-1] - t[0])
    f = np.arange(MIN_LINE_HZ, nyq, 0.05)
    p = signal.lombscargle(t - t[0], x - x.mean(), 2 * np.pi * f)
    return _peaks(f, p, RATIO_MIN)


def line_amplitude(rate: float, v: np.ndarray, f_hz: float, half_width_hz: float = 0.5) -> float:
    """Sine amplitude of a line from the Welch spectrum: the power above the local level
    within ±``half_width_hz`` (A = √(2·P))."""
    f, p = signal.welch(v, fs=rate, nperseg=min(NPERSEG, len(v) // 4), detrend="linear")
    near = np.abs(f - f_hz) <= LOCAL_HZ
    level = np.median(p[near])
    band = np.abs(f - f_hz) <= half_width_hz
    return float(np.sqrt(2.0 * np.sum(np.clip(p[band] - level, 0.0, None)) * (f[1] - f[0])))


def _fmt(lines, n=8) -> str:
    return " ".join(f"{f:.2f}({r:.0f}x)" for f, r in lines[:n]) or "-"


def report(stem: str) -> None:
    d = load(stem)
    t = d["t_s"]
    dt = np.diff(t)
    print(f"\n== {stem}: {len(t)} samples, {t[-1] - t[0]:.1f} s, mean rate {(len(t) - 1) / (t[-1] - t[0]):.2f} Hz")
    for k in ("rc_throttle", "motor0", "motor1", "motor2", "motor3"):
        print(f"  {k:12s} logged values {np.unique(d[k]).tolist()}")
    vals, cnt = np.unique(np.round(dt * 1e3, 1), return_counts=True)
    print("  sample spacing ms (count): " + ", ".join(f"{v:g} ({c})" for v, c in zip(vals, cnt) if c >= 20))
    rate, ddt, _ = on_uniform_grid(t[1:], dt)
    print(f"  spectrum of the spacing itself: {_fmt(spectral_lines(rate, ddt), 4)}")
    m = np.column_stack([d["mag_x"], d["mag_y"], d["mag_z"]])
    centre = np.array(FC_CENTRE_COUNTS) if "apex5" in stem else m.mean(0)
    chans = {"mag_x": m[:, 0], "mag_y": m[:, 1], "mag_z": m[:, 2], "|m|": np.linalg.norm(m - centre, axis=1)}
    chans.update({k: d[k] for k in ("gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "acc_x_g", "acc_y_g", "acc_z_g", "current_A")})
    for k, v in chans.items():
        rate, u, interp = on_uniform_grid(t, v)
        half = len(u) // 2
        print(f"  {k:11s} Welch{' (interpolated)' if interp else ''}: {_fmt(spectral_lines(rate, u))}")
        if k.startswith("mag"):
            print(f"  {'':11s}   first half: {_fmt(spectral_lines(rate, u[:half]), 5)}; second half: "
                  f"{_fmt(spectral_lines(rate, u[half:]), 5)}")
            print(f"  {'':11s}   Lomb-Scargle on raw times: {_fmt(lomb_scargle_lines(t, v))}")
    if "apex5" in stem:
        for k in ("mag_x", "mag_y", "mag_z"):
            rate, u, _ = on_uniform_grid(t, d[k])
            amps = ", ".join(f"{f} Hz {line_amplitude(rate, u, f) / 30.0:.3f}" for f in (12.3, 28.2, 52.8, 68.7))
            print(f"  {k} line amplitude, µT (3000 LSB/G): {amps}")


def main() -> int:
    for stem in SESSIONS + REFERENCE:
        report(stem)
    print("\nlines both apex5 sessions carry on an axis (carried_lines, Hz):")
    for stem in SESSIONS:
        d = load(stem)
        m = np.column_stack([d["mag_x"], d["mag_y"], d["mag_z"]])
        print(f"  {stem}: {', '.join(f'{f:.2f}' for f in carried_lines(d['t_s'], m))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
