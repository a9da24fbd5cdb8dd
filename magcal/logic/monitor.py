"""Does the stored calibration still fit the live data? A statistical drift test (pure).

A new hard iron δ (a payload bolted on, a magnetised screw) shifts every measurement:
m' = m + δ, so the corrected field h' = W(m' − b) = h + Wδ and, to first order,

    e = |h'| − r  ≈  c(t) + u·d + noise,     u = h/|h|,  d = Wδ,  c(t) a change of field radius

— a degree-1 pattern over the direction sphere. For each window of ``window`` valid samples the
monitor fits θ = (c₀, d, c₁) by least squares on X = [1, u, s], s the sample's place in the
window (−½ … ½): the field's own magnitude is not constant (iron nearby moves, the local field
wanders), and its change, level and trend within the window, is a nuisance, not a hard iron.
Samples far beyond the window's robust spread are left out first (``window_fit``). Samples are
autocorrelated (slow motion, temperature, the fit's own small misfit move together), so the
noise is not white: the variance σ² of the window residuals and the integrated-autocorrelation
factor τ (variance of batch means × batch length / σ², "effective sample size" n/τ) are
estimated while the calibration is known good (the first ``baseline_windows`` windows after it
was loaded or written), together with a reference and the spread of windows around it.

Each later window is tested against the reference, in the directions the window's motion
determines (eigenvectors of its information that carry some; Δ the difference there):

* the hard-iron test, whenever the window's directions determine some direction of d with
  c₀ and c₁ free (the Schur complement S of XᵀX): Δ = d − d₀ with covariance
  C = σ²τ (S⁻¹ + S₀⁻¹) + q I. q is the sensor's own offset wander between a window and the
  reference, in µT² per direction: an additive spread that does not shrink as a window sees
  more directions (the noise part does). It is estimated from the baseline windows, each
  tested against the ones before it, and then from every test window that passes, with a
  memory ``SPREAD_MEMORY`` times the reference's — a slow wander's size changes over minutes,
  and a spread measured on the first minute alone was beaten 5 to 60 times as often as stated
  on twins of real recordings (bench/twin_monitor.py); but a narrow-band wander also has calm
  stretches, and a spread as short-lived as the reference read "no wander" in them (q = 0,
  the noise alone) just before the wander rose again: on twins of a quadcopter's QMC5883L
  every alarm came from such windows (bench/README.md).
* the combined test, on a still board (its one direction sees c + u·d together): θ = (c, d)
  on X = [1, u], C = φσ²τ ((XᵀX)⁻¹ + (X₀ᵀX₀)⁻¹), φ ≥ 1 the baseline windows' dispersion
  around each other (a calibration slightly off in soft iron leaves a residual whose degree-1
  projection depends on which directions a window sees; φ keeps that from alarming).

T = Δᵀ C⁻¹ Δ; under "nothing changed" T/k ~ F(k, ν), k the tested dimensions and ν the degrees
of freedom of the estimated scale (the baseline's batches for σ²τ, or the effective number of
comparisons behind q or φ when those are in use). The calibration no longer fits when the
p-value is below ``alpha`` — the configured false-alarm probability of one test, not a fixed
threshold in µT. ``estimated_shift_ut`` turns the difference back into the sensor-frame offset
change W⁻¹(d − d₀) so a log line can say how large the new hard iron is.

The reference tracks: each test window that passes joins it with exponential forgetting, its
memory as long as the baseline (a real sensor's offset wanders slowly, docs/sensor-model.md);
a window that alarms never joins, so a new hard iron stays loud.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ..core.calibration import Calibration
from ..fit import tails
from ..fit.outliers import robust_sigma

EIG_FLOOR = 2e-3  # a direction of θ is tested when its share of its information / n exceeds this
MIN_BATCHES = 10  # batches per window for the batch-means (autocorrelation) estimate
TAIL = 0.01  # expected Gaussian samples per window that the outlier bound leaves out by chance
REJECT_PASSES = 10  # at most this many refits, each leaving out the samples beyond that bound
STATE_VERSION = 2
SPREAD_MEMORY = 4  # the spread (φ, q) forgets this many times more slowly than the reference


def _clipped(moments: np.ndarray, c: float) -> np.ndarray:
    """A comparison's moments as if its difference Δ were shrunk so that T² became c·T²: the
    two moments quadratic in Δ scaled by c, the geometry terms kept."""
    return moments * np.array([c, 1.0, 1.0, c, 1.0])


class Phase(enum.Enum):
    """Where the monitor is: learning the noise from its first windows, or testing."""

    BASELINE = "baseline"
    TEST = "test"


class WindowTest(enum.Enum):
    """Which test a window gets: the hard iron d with the field's magnitude free (the window's
    directions determine some direction of d), or c and d together (a still board)."""

    HARD_IRON = "hard_iron"
    COMBINED = "combined"


HARD_IRON, COMBINED = WindowTest.HARD_IRON, WindowTest.COMBINED
_D, _NUISANCE = [1, 2, 3], [0, 4]  # places of d and of (c₀, c₁) in θ


@dataclass(frozen=True)
class WindowVerdict:
    """One window's verdict: in which ``phase`` and, when testing, by which ``test``."""

    window: int
    phase: Phase
    n: int
    statistic: float
    threshold: float
    df: int
    p_value: float
    drifted: bool
    rms_ut: float  # RMS of |h| − r over the window
    estimated_shift_ut: tuple  # sensor-frame offset change the window suggests (µT)
    test: WindowTest | None = None

    def to_dict(self) -> dict:
        return {
            "window": self.window,
            "phase": self.phase.value,
            "test": self.test.value if self.test else None,
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
    """The degree-1 residual fit of one window (pure): XᵀX and Xᵀe on X = [1, u, s], residual
    sums, batch means.

    Samples whose residual lies beyond the Gaussian bound one window's worth of samples would
    pass by chance (``TAIL`` per window, from the residual's robust σ) are left out and the fit
    repeated: a disturbance of the field — iron carried past, a current switched for a moment —
    holds a few samples far off for a while and then lets go; it is not a new hard iron, which
    moves every sample of the window by u·d."""
    h = cal.correct(m_ut, channels)
    norm = np.linalg.norm(h, axis=1)
    e = norm - cal.field_ut
    s = (np.arange(len(e)) + 0.5) / len(e) - 0.5
    x = np.column_stack([np.ones(len(e)), h / norm[:, None], s])
    keep = _near(e, float(tails.norm_isf(TAIL / (2 * len(e)))))
    a, b = x[keep].T @ x[keep], x[keep].T @ e[keep]
    r = e - x @ (np.linalg.pinv(a, rcond=1e-10, hermitian=True) @ b)
    r = np.where(keep, r, 0.0)  # a left-out sample carries no residual into σ or the batch means
    batch = max(1, len(r) // MIN_BATCHES)
    nb = len(r) // batch
    means = r[: nb * batch].reshape(nb, batch).mean(axis=1)
    return {
        "a": a,
        "b": b,
        "rss": float(r @ r),
        "dof": max(1, int(np.count_nonzero(keep)) - 5),
        "bm_ss": float(batch * (means @ means)),  # Σ batch·mean² (≈ nb·σ²τ)
        "nb": nb,
        "rms_ut": float(np.sqrt(np.mean(e * e))),
    }


def _near(e: np.ndarray, bound: float) -> np.ndarray:
    """The samples within ``bound`` robust σ of the window's median |h| − r, the σ and median
    taken again over those kept until no sample changes side (at most ``REJECT_PASSES`` times).
    Judged on |h| − r itself, not on a fit's residual: a fit through a window whose directions
    are an arc extrapolates where samples were left out and would take them back."""
    keep = np.ones(len(e), dtype=bool)
    for _ in range(REJECT_PASSES):
        near = np.abs(e - np.median(e[keep])) <= bound * max(robust_sigma(e[keep]), 1e-12)
        if np.count_nonzero(near) < 4 * MIN_BATCHES or np.array_equal(near, keep):
            break
        keep = near
    return keep


def window_parts(a: np.ndarray, b: np.ndarray, test: WindowTest) -> tuple[np.ndarray, np.ndarray]:
    """(estimate, information) of one window for ``test`` (pure), from its sums on [1, u, s]:
    ``combined`` θ = (c, d) on [1, u] alone; ``hard_iron`` d with c₀ and c₁ free — the Schur
    complement S = A_dd − A_dN A_NN⁻¹ A_Nd, so sums of S and S·d over windows estimate one d
    while each window keeps its own field magnitude."""
    if test is COMBINED:
        a4 = a[:4, :4]
        return np.linalg.pinv(a4, rcond=1e-10, hermitian=True) @ b[:4], a4
    k = a[np.ix_(_D, _NUISANCE)] @ np.linalg.pinv(a[np.ix_(_NUISANCE, _NUISANCE)], rcond=1e-10, hermitian=True)
    s = a[np.ix_(_D, _D)] - k @ a[np.ix_(_NUISANCE, _D)]
    return np.linalg.pinv(s, rcond=1e-10, hermitian=True) @ (b[_D] - k @ b[_NUISANCE]), s


def statistic(delta_full, info, n, ref_inv, var, scale=(1.0, 0.0)):
    """T² of a difference in the directions this window's information determines under the
    covariance φN + qI, N = var·(Λ⁻¹ + Vᵀ R V) the noise part; its dimension k, the tested part of
    the difference, and the comparison's moments for the spread (``Reference.spread``) (pure)."""
    lam, vec = np.linalg.eigh(info)
    keep = lam > EIG_FLOOR * n
    k = int(np.count_nonzero(keep))
    if k == 0:
        return 0.0, 0, np.zeros(len(delta_full)), np.zeros(5)
    v = vec[:, keep]
    delta = v.T @ delta_full
    noise = var * (np.diag(1.0 / lam[keep]) + v.T @ ref_inv @ v)
    phi, q = scale
    t2 = float(delta @ np.linalg.solve(phi * noise + q * np.eye(k), delta))
    n_inv = np.linalg.inv(noise)
    moments = np.array([delta @ n_inv @ delta, k, np.trace(n_inv), delta @ delta, np.trace(noise)])
    return t2, k, v @ delta, moments


class Spread:
    """The windows' spread around a reference, as forgetting sums of each comparison's moments
    (``statistic``) with weights for their effective count.

    The model: E[ΔΔᵀ] = φN + qI — φ ≥ 1 scales the noise part N (a calibration slightly off
    leaves a residual whose projection depends on which directions a window sees, so it grows
    as N does), q ≥ 0 adds the sensor's own wander between a window and the reference (µT²
    per direction, whatever the window sees). Two moment equations, summed over comparisons:
    Σ ΔᵀN⁻¹Δ = φ Σk + q Σ tr N⁻¹ and Σ |Δ|² = φ Σ tr N + q Σk."""

    def __init__(self, forget: float):
        self.forget = forget
        self.moments, self.w, self.w2 = np.zeros(5), 0.0, 0.0

    def add(self, moments) -> None:
        f = self.forget
        self.moments = f * self.moments + moments
        self.w, self.w2 = f * self.w + 1.0, f * f * self.w2 + 1.0

    def scale(self) -> tuple[float, float, float]:
        """(φ ≥ 1, q ≥ 0 in µT², the effective number of comparisons behind them)."""
        m_inv, k, tr_inv, m_sq, tr_n = self.moments
        if k <= 0:
            return 1.0, 0.0, 0.0
        det = k * k - tr_inv * tr_n
        phi, q = -1.0, -1.0
        if abs(det) > 1e-9 * k * k:  # the windows' geometries differ enough to tell φ from q
            phi, q = (m_inv * k - tr_inv * m_sq) / det, (k * m_sq - tr_n * m_inv) / det
        if q < 0:
            phi, q = max(1.0, m_inv / k), 0.0
        elif phi < 1:
            phi, q = 1.0, max(0.0, (m_sq - tr_n) / k)
        return float(phi), float(q), self.w * self.w / self.w2

    def to_state(self) -> dict:
        return {"moments": self.moments.tolist(), "w": [self.w, self.w2]}

    def restore(self, d: dict) -> None:
        self.moments = np.asarray(d["moments"], dtype=np.float64).reshape(5)
        self.w, self.w2 = (float(v) for v in d["w"])


class Reference:
    """One test's tracked reference: forgetting sums of the windows' information and
    information × estimate, and the windows' spread around it over two memories — the
    reference's own (a wander that grows is learned within a few windows) and ``SPREAD_MEMORY``
    times longer (a narrow-band wander has calm stretches, and the short memory alone reads
    "no wander" in them just before it rises again). A window is judged under whichever
    of the two allows the larger spread for it."""

    def __init__(self, dim: int, forget: float):
        self.forget = forget
        self.a, self.b = np.zeros((dim, dim)), np.zeros(dim)
        self.spreads = (Spread(forget), Spread(1.0 - (1.0 - forget) / SPREAD_MEMORY))

    def estimate(self):
        inv = np.linalg.pinv(self.a, rcond=1e-10, hermitian=True)
        return inv @ self.b, inv

    def join(self, theta, info) -> None:
        self.a = self.forget * self.a + info
        self.b = self.forget * self.b + info @ theta

    def spread(self, moments) -> None:
        for sp in self.spreads:
            sp.add(moments)

    def scale(self) -> tuple[float, float, float]:
        """The short memory's (φ, q, effective comparisons): what ``status`` reports."""
        return self.spreads[0].scale()

    def to_state(self) -> dict:
        short, long = (sp.to_state() for sp in self.spreads)
        return {"a": self.a.tolist(), "b": self.b.tolist(), **short, "long": long}

    @classmethod
    def from_state(cls, d: dict, dim: int, forget: float) -> "Reference":
        """A state written before the long memory existed starts it from the short one."""
        ref = cls(dim, forget)
        ref.a = np.asarray(d["a"], dtype=np.float64).reshape(dim, dim)
        ref.b = np.asarray(d["b"], dtype=np.float64).reshape(dim)
        ref.spreads[0].restore(d)
        ref.spreads[1].restore(d.get("long", d))
        return ref


class DriftMonitor:
    """Feed valid samples (µT, sensor frame) with ``add``; it returns a WindowVerdict per full window."""

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
        self.last: WindowVerdict | None = None
        self._ref = {HARD_IRON: Reference(3, self._forget), COMBINED: Reference(4, self._forget)}
        self._noise_sums = [0.0, 0, 0.0, 0]  # Σ rss, Σ dof, Σ batch-mean squares, Σ batches (baseline)
        self._base_done = 0
        self._base_windows: list[tuple[np.ndarray, np.ndarray]] = []  # (A, b) on [1, u, s] per window

    # -- feeding ---------------------------------------------------------------------------------
    @property
    def phase(self) -> Phase:
        return Phase.BASELINE if self._base_done < self.baseline_windows else Phase.TEST

    @property
    def drifted(self) -> bool:
        return self.first_alarm_window is not None

    def add(self, m_ut, temp_c=None) -> list[WindowVerdict]:
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

    def _process(self, m: np.ndarray, temp: np.ndarray) -> WindowVerdict:
        channels = None
        if "temp_c" in self.calibration.coef_ut_per_unit and np.all(np.isfinite(temp)):
            channels = {"temp_c": temp}
        w = window_fit(self.calibration, m, channels)
        self.windows += 1
        if self.phase is Phase.BASELINE:
            v = self._learn(w, len(m))
        else:
            v = self._test(w, len(m))
        self.last = v
        return v

    def _learn(self, w: dict, n: int) -> WindowVerdict:
        """A baseline window: its noise sums, and its place in the references."""
        for i, key in enumerate(("rss", "dof", "bm_ss", "nb")):
            self._noise_sums[i] += w[key]
        self._base_done += 1
        self._base_windows.append((w["a"], w["b"]))
        self._join(w)
        if self._base_done == self.baseline_windows:
            self._spread()
        return WindowVerdict(self.windows, Phase.BASELINE, n, float("nan"), float("nan"), 0, float("nan"), False,
                             w["rms_ut"], (0.0, 0.0, 0.0))

    # -- the test ----------------------------------------------------------------------------------
    def noise(self) -> tuple[float, float]:
        """(σ of the window residuals in µT, τ the autocorrelation factor ≥ 1) from the baseline."""
        rss, dof, bm, nb = self._noise_sums
        sigma2 = rss / max(1, dof)
        tau = max(1.0, (bm / max(1, nb)) / sigma2) if sigma2 > 0 else 1.0
        return float(np.sqrt(sigma2)), float(tau)

    def _var(self) -> float:
        sigma, tau = self.noise()
        return max(sigma * sigma * tau, 1e-12)

    def _spread(self) -> None:
        """The baseline windows' spread, in the geometry of every later test: each window from
        the second on compared with the reference the windows before it make (forgetting as
        the tracked reference does); the comparisons' moments start each test's spread."""
        var = self._var()
        refs = {HARD_IRON: Reference(3, self._forget), COMBINED: Reference(4, self._forget)}
        for i, (a, b) in enumerate(self._base_windows):
            for test, ref in refs.items():
                theta, info = window_parts(a, b, test)
                if i:
                    theta0, ref_inv = ref.estimate()
                    _, k, _, moments = statistic(theta - theta0, info, self.window, ref_inv, var)
                    if k:
                        self._ref[test].spread(moments)
                ref.join(theta, info)

    def _which(self, w: dict) -> str:
        """The hard-iron test when the window determines some direction of d with the field's
        magnitude free; else (a still board) the combined test."""
        _, s = window_parts(w["a"], w["b"], HARD_IRON)
        return HARD_IRON if np.linalg.eigvalsh(s)[-1] > EIG_FLOOR * self.window else COMBINED

    def _test(self, w: dict, n: int) -> WindowVerdict:
        test = self._which(w)
        theta, info = window_parts(w["a"], w["b"], test)
        ref = self._ref[test]
        theta0, ref_inv = ref.estimate()
        judged = [self._judge(theta - theta0, info, n, ref_inv, sp.scale()) for sp in ref.spreads]
        t2, k, seen, moments, p, threshold = max(judged, key=lambda j: j[4])
        if k == 0:
            return WindowVerdict(self.windows, Phase.TEST, n, 0.0, float("inf"), 0, 1.0, False, w["rms_ut"], (0.0, 0.0, 0.0),
                                 test)
        drifted = p < self.alpha
        shift = self._w_inv @ (seen if test is HARD_IRON else seen[1:])  # e ≈ u·Wδ ⇒ δ = W⁻¹d
        if drifted:
            self.alarms += 1
            if self.first_alarm_window is None:
                self.first_alarm_window = self.windows
            # the spread learns from it clipped to the threshold (a Huber-type scale estimate):
            # a wander that has grown is learned, a new hard iron cannot swell it beyond that
            ref.spread(_clipped(moments, threshold / t2))
        else:
            ref.spread(moments)
            self._join(w)
        return WindowVerdict(self.windows, Phase.TEST, n, t2, threshold, k, p, drifted,
                             w["rms_ut"], tuple(float(s) for s in shift), test)

    def _judge(self, delta, info, n, ref_inv, scale):
        """(T², k, the tested difference, its moments, p, threshold) under one spread."""
        phi, q, nu = scale
        # the scale is estimated: its dof are the baseline batches (σ²τ) or, when the windows
        # spread more than the noise explains, the comparisons behind φ and q — at most as many
        # as the baseline's: consecutive comparisons share most of their reference and of the
        # wander, so however long the monitor has run its spread rests on about that many
        # independent ones
        nu = min(nu, self.baseline_windows - 1) if (phi > 1.0 or q > 0.0) else self._noise_sums[3] - 1
        nu = max(1.0, nu)
        t2, k, seen, moments = statistic(delta, info, n, ref_inv, self._var(), (phi, q))
        if k == 0:
            return t2, k, seen, moments, 1.0, float("inf")
        return t2, k, seen, moments, float(tails.f_sf(t2 / k, k, nu)), float(k * tails.f_isf(self.alpha, k, nu))

    def _join(self, w: dict) -> None:
        """A baseline window, or a test window that passed, joins both references, which forget
        at the rate that keeps them as large as the baseline (λ = 1 − 1/(baseline_windows + 1)):
        the reference follows the sensor's own slow wander, while a window that alarmed is never
        absorbed, so a new hard iron stays loud."""
        for test, ref in self._ref.items():
            ref.join(*window_parts(w["a"], w["b"], test))

    # -- persistence -----------------------------------------------------------------------------
    def to_state(self) -> dict:
        return {
            "version": STATE_VERSION,
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
                "noise": list(self._noise_sums),
                "done": self._base_done,
                "windows": [[a.tolist(), b.tolist()] for a, b in self._base_windows],
                "references": {test.value: ref.to_state() for test, ref in self._ref.items()},
            },
        }

    @classmethod
    def from_state(cls, d: dict) -> "DriftMonitor":
        """The monitor a state describes. A state of the first version (its reference in
        another form) gives a monitor that learns its baseline again, its counts kept."""
        try:
            mon = cls(Calibration.from_dict(d["calibration"]), d["window"], d["alpha"], d["baseline_windows"])
            buf = np.asarray(d["buffer_ut"], dtype=np.float64).reshape(-1, 3)
            if len(buf) >= mon.window:
                raise ValueError("monitor buffer longer than its window")
            mon.windows = int(d["windows"])
            mon.alarms = int(d["alarms"])
            mon.first_alarm_window = d["first_alarm_window"]
            if d.get("version", 1) != STATE_VERSION:
                return mon
            mon._buf[: len(buf)] = buf
            mon._temp[: len(buf)] = [np.nan if x is None else float(x) for x in d["buffer_temp_c"]]
            mon._fill = len(buf)
            mon._restore_baseline(d["baseline"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"monitor state is malformed: {exc!r}") from None
        return mon

    def _restore_baseline(self, base: dict) -> None:
        rss, dof, bm, nb = base["noise"]
        self._noise_sums = [float(rss), int(dof), float(bm), int(nb)]
        self._base_done = int(base["done"])
        self._base_windows = [(np.asarray(a, dtype=np.float64).reshape(5, 5), np.asarray(b, dtype=np.float64).reshape(5))
                              for a, b in base["windows"]]
        refs = base["references"]
        self._ref = {HARD_IRON: Reference.from_state(refs[HARD_IRON.value], 3, self._forget),
                     COMBINED: Reference.from_state(refs[COMBINED.value], 4, self._forget)}

    def status(self) -> dict:
        sigma, tau = self.noise() if self._noise_sums[3] else (None, None)
        phi, q, _ = self._ref[HARD_IRON].scale()
        return {
            "phase": "drifted" if self.drifted else self.phase.value,
            "windows": self.windows,
            "alarms": self.alarms,
            "first_alarm_window": self.first_alarm_window,
            "noise_ut": sigma,
            "autocorrelation_factor": tau,
            "dispersion_factor": phi,
            "offset_wander_ut": float(np.sqrt(q)),
            "pending_samples": self._fill,
            "last": self.last.to_dict() if self.last else None,
        }
