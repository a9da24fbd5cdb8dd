"""Does the stored calibration still fit the live data? A statistical drift test (pure).

A new hard iron δ (a payload bolted on, a magnetised screw) shifts every measurement:
m' = m + δ, so the corrected field h' = W(m' − b) = h + Wδ and, to first order,

    e = |h'| − r  ≈  c + u·d + noise,       u = h/|h|,  d = Wδ,  c a change of field radius

— a degree-1 pattern over the direction sphere. For each window of ``window`` valid samples the
monitor fits θ = (c, d) by least squares on X = [1, u]. Samples are autocorrelated (slow motion,
temperature, the fit's own small misfit move together), so the noise is not white: the variance
σ² of the window residuals and the integrated-autocorrelation factor τ (variance of batch means
× batch length / σ², "effective sample size" n/τ) are estimated while the calibration is known
good (the first ``baseline_windows`` windows after it was loaded or written), together with the
baseline θ₀ and its covariance, and a dispersion factor φ ≥ 1: each baseline window tested
against the others — a calibration that is slightly off in soft iron leaves a residual whose
degree-1 projection depends on which directions a window sees, and φ scales the variance so that
this, which is not a change, does not raise alarms.

Each later window is tested: Δ = θ − θ₀ in the directions the window's motion determines
(eigenvectors of XᵀX that carry information; a still board tests only the one combination it
sees), C = φσ²τ ((XᵀX)⁻¹ + (X₀ᵀX₀)⁻¹), T = Δᵀ C⁻¹ Δ; under "nothing changed" T/k ~ F(k, ν) with
k the tested dimensions and ν the degrees of freedom of the estimated scale (the baseline's
batches for σ²τ, or the leave-one-out dimensions when φ > 1). The calibration no longer
fits when the p-value is below ``alpha`` — the configured false-alarm probability of one test,
not a fixed threshold in µT. ``estimated_shift_ut`` turns d back into the sensor-frame offset
change W⁻¹(d − d₀) so a log line can say how large the new hard iron is.

A real sensor's offset wanders slowly (docs/sensor-model.md): against a reference frozen at the
baseline, the wander alone drove the rate of false alarms to 3–5× alpha on twins of real
recordings (bench/twin_monitor.py). The reference θ₀ therefore tracks: each test window that
passes joins it with exponential forgetting, its memory as long as the baseline, so the wander
is judged over the span the dispersion φ was measured on; a window that alarms never joins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..core.calibration import Calibration

EIG_FLOOR = 2e-3  # a direction of θ is tested when its share of XᵀX/n exceeds this
MIN_BATCHES = 10  # batches per window for the batch-means (autocorrelation) estimate


@dataclass(frozen=True)
class Verdict:
    """One window's test. ``phase`` is ``baseline`` (learning the noise) or ``test``."""

    window: int
    phase: str
    n: int
    statistic: float
    threshold: float
    df: int
    p_value: float
    drifted: bool
    rms_ut: float  # RMS of |h| − r over the window
    estimated_shift_ut: tuple  # sensor-frame offset change the window suggests (µT)

    def to_dict(self) -> dict:
        return {
            "window": self.window,
            "phase": self.phase,
            "n": self.n,
            "statistic": _f(self.statistic),
            "threshold": _f(self.threshold),
            "df": self.df,
            "p_value": _f(self.p_value),
            "drifted": self.drifted,
            "rms_ut": _f(self.rms_ut),
            "estimated_shift_ut": [_f(v) for v in self.estimated_shift_ut],
        }


def _f(x):
    x = float(x)
    return x if np.isfinite(x) else None


def window_fit(cal: Calibration, m_ut: np.ndarray, channels=None) -> dict:
    """The degree-1 residual fit of one window (pure): θ, XᵀX, residual sums, batch means."""
    h = cal.correct(m_ut, channels)
    norm = np.linalg.norm(h, axis=1)
    e = norm - cal.field_ut
    u = h / norm[:, None]
    x = np.column_stack([np.ones(len(e)), u])
    a = x.T @ x
    b = x.T @ e
    theta = np.linalg.pinv(a, rcond=1e-10, hermitian=True) @ b
    r = e - x @ theta
    batch = max(1, len(r) // MIN_BATCHES)
    nb = len(r) // batch
    means = r[: nb * batch].reshape(nb, batch).mean(axis=1)
    return {
        "theta": theta,
        "a": a,
        "b": b,
        "rss": float(r @ r),
        "dof": max(1, len(r) - 4),
        "bm_ss": float(batch * (means @ means)),  # Σ batch·mean² (≈ nb·σ²τ)
        "nb": nb,
        "rms_ut": float(np.sqrt(np.mean(e * e))),
    }


class DriftMonitor:
    """Feed valid samples (µT, sensor frame) with ``add``; it returns a Verdict per full window."""

    def __init__(self, calibration: Calibration, window: int = 500, alpha: float = 0.001, baseline_windows: int = 8):
        if window < 4 * MIN_BATCHES:
            raise ValueError(f"monitor window must hold at least {4 * MIN_BATCHES} samples, got {window}")
        if not 0 < alpha < 0.5:
            raise ValueError(f"monitor alpha must be in (0, 0.5), got {alpha}")
        if baseline_windows < 1:
            raise ValueError("monitor needs at least one baseline window")
        self.calibration = calibration
        self.window = int(window)
        self.alpha = float(alpha)
        self.baseline_windows = int(baseline_windows)
        self._forget = 1.0 - 1.0 / (self.baseline_windows + 1)  # the reference's memory: the baseline
        self._w_inv = np.linalg.inv(calibration.soft_iron)
        self._buf = np.empty((self.window, 3))
        self._temp = np.empty(self.window)
        self._fill = 0
        self.windows = 0
        self.alarms = 0
        self.first_alarm_window: int | None = None
        self.last: Verdict | None = None
        # baseline sums
        self._a0 = np.zeros((4, 4))
        self._b0 = np.zeros(4)
        self._rss0 = 0.0
        self._dof0 = 0
        self._bm0 = 0.0
        self._nb0 = 0
        self._base_done = 0
        self._base_windows: list[tuple[np.ndarray, np.ndarray]] = []  # (θ, XᵀX) per baseline window
        self._phi = 1.0  # over-dispersion of θ between baseline windows (≥ 1)
        self._phi_dof = 0

    # -- feeding ---------------------------------------------------------------------------------
    @property
    def phase(self) -> str:
        return "baseline" if self._base_done < self.baseline_windows else "test"

    @property
    def drifted(self) -> bool:
        return self.first_alarm_window is not None

    def add(self, m_ut, temp_c=None) -> list[Verdict]:
        """Samples (n, 3) µT (and their die temperatures, when the calibration uses them)."""
        m = np.atleast_2d(np.asarray(m_ut, dtype=np.float64))
        t = None if temp_c is None else np.broadcast_to(np.asarray(temp_c, dtype=np.float64), (len(m),))
        out = []
        i = 0
        while i < len(m):
            take = min(self.window - self._fill, len(m) - i)
            self._buf[self._fill : self._fill + take] = m[i : i + take]
            self._temp[self._fill : self._fill + take] = np.nan if t is None else t[i : i + take]
            self._fill += take
            i += take
            if self._fill == self.window:
                self._fill = 0
                out.append(self._process(self._buf, self._temp))
        return out

    def _process(self, m: np.ndarray, temp: np.ndarray) -> Verdict:
        channels = None
        if "temp_c" in self.calibration.coef_ut_per_unit and np.all(np.isfinite(temp)):
            channels = {"temp_c": temp}
        w = window_fit(self.calibration, m, channels)
        self.windows += 1
        if self.phase == "baseline":
            self._a0 = self._forget * self._a0 + w["a"]
            self._b0 = self._forget * self._b0 + w["b"]
            self._rss0 += w["rss"]
            self._dof0 += w["dof"]
            self._bm0 += w["bm_ss"]
            self._nb0 += w["nb"]
            self._base_done += 1
            self._base_windows.append((w["theta"], w["a"]))
            if self._base_done == self.baseline_windows:
                self._phi, self._phi_dof = self._dispersion()
            v = Verdict(self.windows, "baseline", len(m), float("nan"), float("nan"), 0, float("nan"), False,
                        w["rms_ut"], (0.0, 0.0, 0.0))
        else:
            v = self._test(w, len(m))
        self.last = v
        return v

    # -- the test ----------------------------------------------------------------------------------
    def noise(self) -> tuple[float, float]:
        """(σ of the window residuals in µT, τ the autocorrelation factor ≥ 1) from the baseline."""
        sigma2 = self._rss0 / max(1, self._dof0)
        tau = max(1.0, (self._bm0 / max(1, self._nb0)) / sigma2) if sigma2 > 0 else 1.0
        return float(np.sqrt(sigma2)), float(tau)

    def _baseline(self):
        pinv = np.linalg.pinv(self._a0, rcond=1e-10, hermitian=True)
        return pinv @ self._b0, pinv

    @staticmethod
    def _statistic(theta, a, n, theta0, a0_inv, var):
        """T² of θ − θ₀ in the directions this window determines, its dimension k, and the
        tested part of the difference (4-vector)."""
        lam, vec = np.linalg.eigh(a)
        keep = lam > EIG_FLOOR * n
        k = int(np.count_nonzero(keep))
        if k == 0:
            return 0.0, 0, np.zeros(4)
        v = vec[:, keep]
        delta = v.T @ (theta - theta0)
        cov = var * (np.diag(1.0 / lam[keep]) + v.T @ a0_inv @ v)
        return float(delta @ np.linalg.solve(cov, delta)), k, v @ delta

    def _dispersion(self) -> tuple[float, int]:
        """How much more θ varies between windows than the noise explains, in the geometry of
        every later test: each baseline window from the second on tested against the reference
        the windows before it make (forgetting as the tracked reference does), φ = ΣT²/Σk ≥ 1.
        It absorbs the sensor's slow offset wander over that span and a small misfit of the
        calibration whose degree-1 projection depends on which directions a window sees."""
        if len(self._base_windows) < 2:
            return 1.0, 0
        sigma, tau = self.noise()
        var = max(sigma * sigma * tau, 1e-12)
        t2_sum, k_sum = 0.0, 0
        a_ref, b_ref = np.zeros((4, 4)), np.zeros(4)
        for i, (theta, a) in enumerate(self._base_windows):
            if i:
                ref_inv = np.linalg.pinv(a_ref, rcond=1e-10, hermitian=True)
                t2, k, _ = self._statistic(theta, a, self.window, ref_inv @ b_ref, ref_inv, var)
                t2_sum += t2
                k_sum += k
            a_ref = self._forget * a_ref + a
            b_ref = self._forget * b_ref + a @ theta
        if k_sum == 0:
            return 1.0, 0
        # dof of φ: one per comparison, not per dimension — a wander moves every dimension of
        # a window together, so the k dimensions of one comparison are not independent
        return max(1.0, t2_sum / k_sum), len(self._base_windows) - 1

    def _test(self, w: dict, n: int) -> Verdict:
        sigma, tau = self.noise()
        var = max(sigma * sigma * tau, 1e-12) * self._phi
        theta0, a0_inv = self._baseline()
        t2, k, seen = self._statistic(w["theta"], w["a"], n, theta0, a0_inv, var)
        if k == 0:
            return Verdict(self.windows, "test", n, 0.0, float("inf"), 0, 1.0, False, w["rms_ut"], (0.0, 0.0, 0.0))
        # the scale σ²τφ is estimated: its dof are the baseline batches (σ²τ) or, when the
        # windows disagree more than the noise explains, the leave-one-out dimensions (φ)
        nu = max(1, self._phi_dof if self._phi > 1.0 else self._nb0 - 1)
        p = float(stats.f.sf(t2 / k, k, nu))
        threshold = float(k * stats.f.isf(self.alpha, k, nu))
        drifted = p < self.alpha
        shift = self._w_inv @ seen[1:]  # only what this window determines; e ≈ u·Wδ ⇒ δ = W⁻¹d
        if drifted:
            self.alarms += 1
            if self.first_alarm_window is None:
                self.first_alarm_window = self.windows
        else:
            self._track(w)
        return Verdict(self.windows, "test", n, t2, threshold, k, p, drifted, w["rms_ut"],
                       tuple(float(s) for s in shift))

    def _track(self, w: dict) -> None:
        """A window that passed joins the reference, which forgets at the rate that keeps it
        as large as the baseline (λ = 1 − 1/baseline_windows): the reference follows the
        sensor's own slow wander — which the dispersion φ, measured over that span, allows
        for — while a window that alarmed is never absorbed, so a new hard iron stays loud."""
        self._a0 = self._forget * self._a0 + w["a"]
        self._b0 = self._forget * self._b0 + w["b"]

    # -- persistence -----------------------------------------------------------------------------
    def to_state(self) -> dict:
        return {
            "calibration": self.calibration.to_dict(),
            "window": self.window,
            "alpha": self.alpha,
            "baseline_windows": self.baseline_windows,
            "buffer_ut": self._buf[: self._fill].tolist(),
            "buffer_temp_c": [None if not np.isfinite(x) else float(x) for x in self._temp[: self._fill]],
            "windows": self.windows,
            "alarms": self.alarms,
            "first_alarm_window": self.first_alarm_window,
            "last": self.last.to_dict() if self.last else None,
            "baseline": {
                "a": self._a0.tolist(),
                "b": self._b0.tolist(),
                "rss": self._rss0,
                "dof": self._dof0,
                "bm_ss": self._bm0,
                "nb": self._nb0,
                "done": self._base_done,
                "windows": [[t.tolist(), a.tolist()] for t, a in self._base_windows],
                "phi": self._phi,
                "phi_dof": self._phi_dof,
            },
        }

    @classmethod
    def from_state(cls, d: dict) -> "DriftMonitor":
        try:
            mon = cls(Calibration.from_dict(d["calibration"]), d["window"], d["alpha"], d["baseline_windows"])
            buf = np.asarray(d["buffer_ut"], dtype=np.float64).reshape(-1, 3)
            if len(buf) >= mon.window:
                raise ValueError("monitor buffer longer than its window")
            mon._buf[: len(buf)] = buf
            mon._temp[: len(buf)] = [np.nan if x is None else float(x) for x in d["buffer_temp_c"]]
            mon._fill = len(buf)
            mon.windows = int(d["windows"])
            mon.alarms = int(d["alarms"])
            mon.first_alarm_window = d["first_alarm_window"]
            base = d["baseline"]
            mon._a0 = np.asarray(base["a"], dtype=np.float64).reshape(4, 4)
            mon._b0 = np.asarray(base["b"], dtype=np.float64).reshape(4)
            mon._rss0 = float(base["rss"])
            mon._dof0 = int(base["dof"])
            mon._bm0 = float(base["bm_ss"])
            mon._nb0 = int(base["nb"])
            mon._base_done = int(base["done"])
            mon._base_windows = [(np.asarray(t, dtype=np.float64).reshape(4), np.asarray(a, dtype=np.float64).reshape(4, 4))
                                 for t, a in base["windows"]]
            mon._phi = float(base["phi"])
            mon._phi_dof = int(base["phi_dof"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"monitor state is malformed: {exc!r}") from None
        return mon

    def status(self) -> dict:
        sigma, tau = self.noise() if self._nb0 else (None, None)
        return {
            "phase": "drifted" if self.drifted else self.phase,
            "windows": self.windows,
            "alarms": self.alarms,
            "first_alarm_window": self.first_alarm_window,
            "noise_ut": sigma,
            "autocorrelation_factor": tau,
            "dispersion_factor": self._phi,
            "pending_samples": self._fill,
            "last": self.last.to_dict() if self.last else None,
        }
