"""Narrowband lines in frequency: a sinusoid added to the sensor axes (mains hum, a rotor, a servo).

A line of amplitude vector ``a`` (sensor frame, µT) at apparent frequency f — the frequency as the
sampling sees it, after aliasing — shows in the radial residual as ``u(t)·W·a·cos(2πft + φ)``: the
six columns ``u_k cos 2πft``, ``u_k sin 2πft`` (k = x, y, z, u the corrected direction) carry it.
The search scans every frequency from ``MIN_CYCLES`` cycles over the recording up to just below
the median sampling rate's Nyquist frequency with the FFT of ``r·u_k`` (uneven timestamps are
gridded on a finer clock; samples that share a grid cell add), whitened by the direction
covariance so that, on white noise, each frequency's explained square is σ²·χ² with six degrees
of freedom. Each frequency is judged against the LOCAL level of that statistic (the running
median over its neighbours, the line's own bins left out): real residuals have a red spectrum
(hand motion, slow offset wander), a line is narrow and a motion misfit broad. The threshold
holds the chance of any false line at ``ALPHA`` over every frequency scanned (Bonferroni over
the independent bins). The strongest passing frequency is refined by least squares on the true
timestamps; a candidate that degree-``DIRECTION_DEGREE`` polynomials of the direction, and
the direction times a slow offset, explain (the motion itself periodic: a calibration-shape
misfit or a wandering hard iron, not interference) is set aside and said so; a line that passes is taken out and the search repeats until none passes.

A logged channel (a current, a throttle, a temperature) that switches or swings periodically puts
its own spectrum — its fundamental, harmonics and their aliases — into the residual wherever the
calibration does not carry its effect in full (no term on it, or a no-lag term for a lagged one).
Such a candidate is the channel's, not a free line, when both hold: the channel's own periodogram
(``spectrum`` of the channel alone, one column) carries a line within ``CHANNEL_NEAR`` independent
bins of it at the same threshold, and one fixed direction at one phase explains the candidate
within chance of the free six columns (χ²₂ at ``ALPHA``) — a channel reaching the sensor through
any lag or time constant moves the field along one direction, with a phase the lag sets. It is set
aside (``ChannelLine``) and said as the channel's structure (``unexplained_structure`` with the
channel in its ``where``), never claimed as a ``narrowband_line``; the channel search
(``channel_forms``) is what fits the channel's form, and where a term it found is kept that
structure is the term's and is not said again (``as_limits``).

``remove`` subtracts each fitted sinusoid from the raw samples. The line has zero mean and does
not depend on orientation, so the calibration refitted on the cleaned samples is the sensor's
own, the same at every time of the recording, with the interference absent.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import optimize

from ...fit import tails
from .. import timewords
from ..channels import TIME, usable
from .base import AXES, REST, Effect, Kind, Located, Residual
from .line_spectrum import ALPHA, GAP, HALF_WINDOW, PAD, Spectrum, sample_interval_s, spectrum

NAME = "narrowband_line"
MAX_LINES = 4
MAX_SET_ASIDE = 6  # direction-harmonic candidates looked past before the search stops
DIRECTION_DEGREE = 4
WANDER_DEGREE = 3
BROAD_SHARE = 0.05  # excess left around a removed line, as a share of its statistic, that makes it broad
AXIS_SHARE = 0.3  # an axis carries the line when its amplitude is this share of the largest
MAINS_HZ = (50.0, 60.0)
MAINS_HARMONICS = 3
CLOCK_SHARE = 2e-4  # how far the median interval may be off the sampling clock
MIN_SAMPLES = 64
CHANNEL_NEAR = 1.0  # independent bins either side of a candidate where a channel's own line is looked for
MAX_CHANNEL_LINES = 12  # candidates set aside as a logged channel's before the search stops
N_PHASES = 48  # phases of the coarse scan for the one-direction fit of a channel's line


@dataclass(frozen=True)
class Line:
    """One fitted line: its frequency and the corrected-frame cos/sin coefficients (3, 2)."""

    frequency_hz: float
    coef: np.ndarray
    cov: np.ndarray  # (6, 6) of the coefficients, columns ordered x cos, y cos, z cos, x sin …
    stat: float  # explained square / local σ²
    level_ut2: float
    explained_ut: np.ndarray  # the line's part of the radial residual, per sample
    t_ref_s: float  # the time of phase zero


# -- one line -----------------------------------------------------------------------------


def columns(t_s: np.ndarray, u: np.ndarray, f_hz: float) -> np.ndarray:
    """The six columns u_k cos 2πf(t − t₀), u_k sin 2πf(t − t₀) (t₀ the first time)."""
    ph = 2 * np.pi * f_hz * (t_s - t_s[0])
    return np.hstack([u * np.cos(ph)[:, None], u * np.sin(ph)[:, None]])


def explained(x: np.ndarray, r_ut: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(explained square, coefficients, (XᵀX)⁻¹) of the least-squares fit of r on x."""
    g = np.linalg.pinv(x.T @ x, rcond=1e-10)
    beta = g @ (x.T @ r_ut)
    return float(beta @ (x.T @ r_ut)), beta, g


def refine(t_s, r_ut, u, f0_hz: float, df_hz: float) -> float:
    """The frequency within ±df of f0 where the six columns explain most (a fine scan, then a
    parabola through the best three)."""
    fs = np.linspace(f0_hz - df_hz, f0_hz + df_hz, 17)
    e = np.array([explained(columns(t_s, u, f), r_ut)[0] for f in fs])
    i = int(np.clip(np.argmax(e), 1, len(fs) - 2))
    den = e[i - 1] - 2 * e[i] + e[i + 1]
    shift = 0.5 * (e[i - 1] - e[i + 1]) / den if den < 0 else 0.0
    return float(fs[i] + np.clip(shift, -1, 1) * (fs[1] - fs[0]))


def fit_line(t_s, r_ut, u, f_hz: float, level_ut2: float) -> Line:
    """The six-column fit at ``f_hz`` judged against the local σ² ``level_ut2``."""
    x = columns(t_s, u, f_hz)
    ess, beta, g = explained(x, r_ut)
    coef = np.stack([beta[:3], beta[3:]], axis=1)
    return Line(f_hz, coef, g * level_ut2, ess / level_ut2, level_ut2, x @ beta, float(t_s[0]))


def direction_basis(u: np.ndarray, t_s: np.ndarray, degree: int = DIRECTION_DEGREE) -> np.ndarray:
    """An orthonormal basis of what the motion itself explains: every polynomial of the
    direction up to ``degree`` (the monomials u_x^a u_y^b u_z^c with c ≤ 1 — on the unit sphere
    u_z² = 1 − u_x² − u_y², so these span them all) and the direction times a slow offset
    (u_k · τ^j, τ time over the span, j ≤ WANDER_DEGREE): a shape misfit and a wandering
    hard iron, both at the motion's own frequencies."""
    cols = [u[:, 0] ** a * u[:, 1] ** b * u[:, 2] ** c
            for c in (0, 1) for a in range(degree + 1) for b in range(degree + 1 - a - c)]
    tau = (t_s - t_s[0]) / max(float(t_s[-1] - t_s[0]), 1e-12) * 2 - 1
    cols += [u[:, k] * tau**j for k in range(3) for j in range(1, WANDER_DEGREE + 1)]
    x = np.column_stack(cols)
    w, v = np.linalg.eigh(x.T @ x)
    keep = w > 1e-10 * w.max()
    return x @ (v[:, keep] / np.sqrt(w[keep]))


def beyond_direction(t_s, r_ut, u, basis: np.ndarray, line: Line) -> float:
    """The line's statistic once every polynomial of the direction has had its say."""
    x = columns(t_s, u, line.frequency_hz)
    x = x - basis @ (basis.T @ x)
    r = r_ut - basis @ (basis.T @ r_ut)
    return explained(x, r)[0] / line.level_ut2


# -- a logged channel's own lines ------------------------------------------------------------


@dataclass(frozen=True)
class ChannelLine:
    """A candidate set aside as a logged channel's: the channel's own line statistic near its
    frequency, and what the free line explains beyond one direction at one phase (over the local
    level; χ²₂ when the channel accounts for it)."""

    frequency_hz: float
    channel: str
    channel_stat: float
    misfit: float
    amplitude_ut: float


def channel_spectra(res: Residual) -> dict[str, Spectrum]:
    """Each usable logged channel's own line statistic (its mean taken out, one column), on the
    same clock and frequencies as the residual's search."""
    one = np.zeros((len(res), 3))
    one[:, 0] = 1.0
    out = {}
    for name, c in res.channels.items():
        c = np.asarray(c, np.float64)
        if name == TIME or c.shape != (len(res),) or not usable(c):
            continue
        sp = spectrum(res.t_s, c - c.mean(), one)
        if sp is not None:
            out[name] = sp
    return out


def carried(sp: Spectrum, f_hz: float) -> float:
    """The channel's strongest line statistic within CHANNEL_NEAR independent bins of ``f_hz``
    where it passes the channel spectrum's own threshold (0 where none does)."""
    df = sp.freq_hz[1] - sp.freq_hz[0] if len(sp.freq_hz) > 1 else np.inf
    near = np.abs(sp.freq_hz - f_hz) <= CHANNEL_NEAR * PAD * df
    top = float(sp.stat[near].max()) if near.any() else 0.0
    return top if top > sp.threshold else 0.0


def one_direction_misfit(t_s, r_ut, u, line: Line) -> float:
    """What the free line's six columns explain beyond the best single direction at a single
    phase (columns u_k cos(2πf(t − t₀) − φ)), over the line's local level."""
    ph = 2 * np.pi * line.frequency_hz * (t_s - t_s[0])

    def lost(phi: float) -> float:
        return -explained(u * np.cos(ph - phi)[:, None], r_ut)[0]

    grid = np.linspace(0.0, np.pi, N_PHASES, endpoint=False)
    at = grid[int(np.argmin([lost(p) for p in grid]))]
    step = np.pi / N_PHASES
    best = optimize.minimize_scalar(lost, bounds=(at - step, at + step), method="bounded", options={"xatol": 1e-6})
    return max(line.stat - min(-best.fun, -lost(at)) / line.level_ut2, 0.0)


def channel_of(scan: "_Scan", line: Line) -> ChannelLine | None:
    """The logged channel whose own line the candidate is (the strongest such channel), or None."""
    owners = [(carried(sp, line.frequency_hz), name) for name, sp in scan.channel_spectra.items()]
    owners = sorted((x for x in owners if x[0] > 0), reverse=True)
    if not owners:
        return None
    misfit = one_direction_misfit(scan.t_s, scan.r_ut, scan.u, line)
    if misfit > tails.chi2_isf(ALPHA, 2):
        return None
    size = float(np.linalg.norm(line.coef))
    return ChannelLine(line.frequency_hz, owners[0][1], owners[0][0], misfit, size)


# -- the search ---------------------------------------------------------------------------


@dataclass
class _Scan:
    """The state of one search: the recording with the lines found so far taken out of its raw
    samples, what was found, what was set aside."""

    res: Residual
    lines: list = field(default_factory=list)
    set_aside_hz: list = field(default_factory=list)  # explained by the direction: the motion's own
    passed_hz: list = field(default_factory=list)  # broad, or not holding on the true timestamps
    threshold: float = np.inf
    beyond_cap_hz: float | None = None  # a candidate still above the threshold when MAX_LINES stopped the search
    channel_lines: list = field(default_factory=list)  # ChannelLine: a logged channel's own, not free lines

    def __post_init__(self):
        self.channel_spectra = channel_spectra(self.res)
        self.refresh()

    def looked_past_hz(self) -> list:
        return self.set_aside_hz + self.passed_hz

    def refresh(self, seen: tuple = ()):
        """Read the residual anew; ``seen``: its spectrum, where already made (one entry)."""
        self.t_s, self.r_ut, self.u = self.res.t_s, self.res.r_ut, self.res.u
        self.basis = None
        self.seen = seen

    def spectrum(self) -> Spectrum | None:
        """``spectrum`` of what the lines found so far leave: made once for each residual (a
        candidate set aside or passed over leaves it as it was, and the next looks at the same)."""
        if not self.seen:
            self.seen = (spectrum(self.t_s, self.r_ut, self.u),)
        return self.seen[0]

    def direction_basis(self) -> np.ndarray:
        if self.basis is None:
            self.basis = direction_basis(self.u, self.t_s)
        return self.basis


def find_lines(res: Residual) -> tuple[list[Line], list[float], float]:
    """(the lines that pass, strongest first; the frequencies set aside as direction harmonics;
    the threshold) in the radial residual of ``res``."""
    scan = _scanned(res)
    return scan.lines, scan.set_aside_hz, scan.threshold


def _scanned(res: Residual) -> _Scan:
    """The search run to its end: no candidate left above the threshold, MAX_LINES found (then
    the strongest candidate still above it is noted, so the report can say more may remain), or
    MAX_SET_ASIDE candidates looked past."""
    scan = _Scan(res)
    while (len(scan.lines) < MAX_LINES and len(scan.set_aside_hz) + len(scan.passed_hz) <= MAX_SET_ASIDE
           and len(scan.channel_lines) < MAX_CHANNEL_LINES):
        if not _next(scan):
            return scan
    if len(scan.lines) == MAX_LINES:
        scan.beyond_cap_hz = _strongest_left_hz(scan)
    return scan


def _strongest_left_hz(scan: _Scan) -> float | None:
    """The frequency of the strongest candidate above the threshold in what the found lines
    leave (not yet judged: it may be a direction harmonic or broad), or None."""
    sp = scan.spectrum()
    if sp is None:
        return None
    stat = _masked(sp, scan.looked_past_hz())
    i = int(np.argmax(stat))
    return float(sp.freq_hz[i]) if stat[i] > sp.threshold else None


def _next(scan: _Scan) -> bool:
    """Find, refine and judge the strongest remaining candidate; False when none passes."""
    sp = scan.spectrum()
    if sp is None:
        return False
    scan.threshold = sp.threshold
    stat = _masked(sp, scan.looked_past_hz())
    i = int(np.argmax(stat))
    if stat[i] <= sp.threshold:
        return False
    line = _plainest(scan, sp, stat, i)
    if line.stat <= sp.threshold:
        scan.passed_hz.append(line.frequency_hz)  # the grid's peak does not hold on the true timestamps
    elif beyond_direction(scan.t_s, scan.r_ut, scan.u, scan.direction_basis(), line) <= sp.threshold:
        scan.set_aside_hz.append(line.frequency_hz)
    elif (owner := channel_of(scan, line)) is not None:
        scan.channel_lines.append(owner)
        _subtract(scan, _without(scan, line))  # its sidelobes and second order go with it, as a free line's do
    else:
        _take_out(scan, line)
    return True


def _plainest(scan: _Scan, sp: Spectrum, stat: np.ndarray, i: int) -> Line:
    """The line behind the peak at bin i. Where the directions turn at a steady rate (flat
    turns), a line on one axis and one turning with the body at its frequency ± the turn rate
    fit the radial residual alike; every strong local peak nearby is fitted on the true
    timestamps and, among those that explain as much as the best (within chance), the one of
    least amplitude is taken: the plainest account."""
    df = sp.freq_hz[1] - sp.freq_hz[0]
    near = np.flatnonzero(np.abs(np.arange(len(stat)) - i) <= HALF_WINDOW * PAD)
    peaks = [j for j in near[1:-1] if stat[j] >= 0.5 * stat[i] and stat[j] >= stat[j - 1] and stat[j] >= stat[j + 1]]
    fits = []
    for j in sorted(set(peaks) | {i}, key=lambda j: -stat[j])[:4]:
        f = refine(scan.t_s, scan.r_ut, scan.u, float(sp.freq_hz[j]), df)
        fits.append(fit_line(scan.t_s, scan.r_ut, scan.u, f, float(sp.level[i])))
    best = max(x.stat for x in fits)
    alike = [x for x in fits if x.stat >= best - 2.0 * sp.dof]
    return min(alike, key=lambda x: float(np.linalg.norm(x.coef)))


def _take_out(scan: _Scan, line: Line) -> None:
    """Keep the line when it is narrow, and take it out of the raw samples (so that its second
    order in |h|, at twice its frequency, goes with it)."""
    rest = _without(scan, line)
    after = spectrum(scan.t_s, rest.r_ut, rest.u)
    if broad(after, line):
        scan.passed_hz.append(line.frequency_hz)
        return
    scan.lines.append(line)
    _subtract(scan, rest, (after,))


def _without(scan: _Scan, line: Line) -> Residual:
    return replace(scan.res, m_ut=scan.res.m_ut - wave_ut(scan.t_s, line, scan.res.calibration.soft_iron))


def _subtract(scan: _Scan, rest: Residual, seen: tuple = ()) -> None:
    scan.res = rest
    scan.refresh(seen)


def wave_ut(t_s: np.ndarray, line: Line, soft_iron: np.ndarray) -> np.ndarray:
    """The line in the sensor frame at times ``t_s`` (n, 3), µT."""
    coef = np.linalg.solve(np.asarray(soft_iron, float), line.coef)
    ph = 2 * np.pi * line.frequency_hz * (t_s - line.t_ref_s)
    return np.outer(np.cos(ph), coef[:, 0]) + np.outer(np.sin(ph), coef[:, 1])


def broad(after: Spectrum, line: Line) -> bool:
    """Whether the excess around the line outlives it: with the sinusoid taken out, the
    independent bins 2 … GAP + 3 away on either side still hold more than BROAD_SHARE of its
    statistic, and more than chance — a motion misfit or a wandering tone, not a line. Both are
    read on one scale, the local level the line leaves: a strong line raises the local level
    around itself (7–30× on real takes with an injected hum), so its statistic against that
    level grows less than its square while the ring after it, read on the level it leaves,
    grows with it — judged on the line's own statistic, the stronger a hum whose amplitude
    follows its load, the surer it was called broad."""
    df = after.freq_hz[1] - after.freq_hz[0]
    off = np.abs(after.freq_hz - line.frequency_hz) / (PAD * df)
    ring = (off >= 2) & (off <= GAP + 3)
    if not ring.any():
        return False
    excess = float(np.mean(after.stat[ring][::PAD]) - after.dof)
    chance = 3.0 * after.dof * np.sqrt(2.0 / after.dof / max(ring.sum() / PAD, 1))
    stat = line.stat * line.level_ut2 / float(np.interp(line.frequency_hz, after.freq_hz, after.level))
    return excess > max(BROAD_SHARE * stat, chance)


def _masked(sp: Spectrum, set_aside_hz: list) -> np.ndarray:
    """The statistic with the bins of set-aside frequencies (± GAP independent bins) cleared."""
    stat = sp.stat.copy()
    width = GAP * PAD * (sp.freq_hz[1] - sp.freq_hz[0]) if len(sp.freq_hz) > 1 else 0.0
    for f in set_aside_hz:
        stat[np.abs(sp.freq_hz - f) <= width] = 0.0
    return stat


# -- what is said -------------------------------------------------------------------------


def mains_alias(f_hz: float, rate_hz: float) -> tuple[float, int] | None:
    """(mains frequency, harmonic) whose alias at the sampling rate ``rate_hz`` lands on
    ``f_hz`` (within 2 %, or what a clock off by CLOCK_SHARE moves the alias by); None
    when none does; the lowest harmonic first, then the nearest. A hint: the sampling clock
    is known only as the median interval."""
    best = None
    for base in MAINS_HZ:
        for h in range(1, MAINS_HARMONICS + 1):
            src = base * h
            alias = abs(src - rate_hz * round(src / rate_hz))
            miss = abs(alias - f_hz)
            if miss <= max(0.02 * f_hz, CLOCK_SHARE * src) and (best is None or (h, miss) < best[:2]):
                best = (h, miss, base)
    return None if best is None else (best[2], best[0])


def raw_frame(line: Line, soft_iron: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos and sin amplitude (3, 2) in the sensor frame, µT; their standard errors (3, 2))."""
    back = np.linalg.inv(np.asarray(soft_iron, float))
    coef = back @ line.coef
    big = np.kron(np.eye(2), back)
    sd = np.sqrt(np.clip(np.diag(big @ line.cov @ big.T), 0, None))
    return coef, np.stack([sd[:3], sd[3:]], axis=1)


def loaded_axes(amp_ut: np.ndarray, sd_ut: np.ndarray) -> list[str]:
    """The axes that carry the line: significant, and at least AXIS_SHARE of the largest."""
    ok = (amp_ut >= AXIS_SHARE * amp_ut.max()) & (amp_ut > 3.0 * sd_ut)
    if not ok.any():
        ok = amp_ut == amp_ut.max()
    return [AXES[k] for k in np.flatnonzero(ok)]


def major_direction(coef_ut: np.ndarray) -> tuple[np.ndarray, float]:
    """(the unit direction of the line's largest swing, its ellipticity: minor / major axis)."""
    v, s, _ = np.linalg.svd(coef_ut)
    d = v[:, 0] * np.sign(v[np.argmax(np.abs(v[:, 0])), 0])
    return d, float(s[1] / s[0]) if s[0] > 0 else 0.0


def located(line: Line, res: Residual, threshold: float, set_aside_hz: list, beyond_cap_hz: float | None = None) -> Located:
    """One line as the typed value the diagnosis reads; ``beyond_cap_hz``: the candidate left
    above the threshold when the search stopped at MAX_LINES (said on the weakest line)."""
    t = res.t_s
    span = float(t[-1] - t[0])
    rate = 1.0 / sample_interval_s(t)
    coef, sd = raw_frame(line, res.calibration.soft_iron)
    amp = np.hypot(coef[:, 0], coef[:, 1])
    amp_sd = np.hypot(sd[:, 0], sd[:, 1]) / np.sqrt(2)
    axes = loaded_axes(amp, amp_sd)
    direction, ellipticity = major_direction(coef)
    f_sd = np.sqrt(12.0 / max(line.stat, 1e-12)) / (2 * np.pi * span)
    mains = mains_alias(line.frequency_hz, rate) if timewords.clocked() else None  # no mains without seconds
    size = float(np.linalg.norm(amp))
    where = {"frequency_hz": line.frequency_hz, "axis": axes[0] if len(axes) == 1 else axes,
             "direction": direction.tolist()}
    params = {"frequency_hz": line.frequency_hz, "frequency_sd_hz": float(f_sd), "amplitude_ut": amp.tolist(),
              "amplitude_sd_ut": amp_sd.tolist(), "cos_ut": coef[:, 0].tolist(), "sin_ut": coef[:, 1].tolist(),
              "t_ref_s": line.t_ref_s, "ellipticity": ellipticity, "sample_rate_hz": rate,
              "mains_hz": mains[0] if mains else None, "mains_harmonic": mains[1] if mains else None}
    evidence = {"statistic": line.stat, "threshold": threshold, "alpha": ALPHA, "dof": 6,
                "local_level_ut": float(np.sqrt(line.level_ut2)), "amplitude_over_floor": size / res.floor_ut,
                "set_aside_direction_harmonics_hz": [float(f) for f in set_aside_hz],
                "next_candidate_beyond_max_lines_hz": beyond_cap_hz}
    summary = _summary(line, f_sd, amp, axes, size / res.floor_ut, mains, rate, set_aside_hz)
    if beyond_cap_hz is not None:
        summary += (f"; the search stops at {MAX_LINES} lines and a candidate at {timewords.frequency(beyond_cap_hz)} still stands above "
                    "the threshold: more lines may remain")
    return Located(NAME, Kind.PHYSICS, summary, where, params, evidence)


def _summary(line, f_sd, amp, axes, over_floor, mains, rate, set_aside_hz) -> str:
    on = f"the {axes[0]} axis" if len(axes) == 1 else "the " + "/".join(axes) + " axes"
    amps = ", ".join(f"{a:.2f}" for a in amp)
    s = (f"a narrowband line at {timewords.frequency(line.frequency_hz)} (±{timewords.frequency(f_sd)}) on {on}, amplitude ({amps}) µT, "
         f"{over_floor:.1f}× the recording's floor and {line.stat / 6:.0f}× the local spectral level")
    if mains:
        which = f"{mains[0]:.0f} Hz mains" if mains[1] == 1 else f"harmonic {mains[1]} of {mains[0]:.0f} Hz mains"
        s += f"; consistent with {which} aliased by the {rate:.1f} Hz sample clock (a hint, not a fact)"
    if set_aside_hz:
        s += ("; set aside as explained by the motion itself (shape misfit or offset wander at its own frequencies, not interference): "
              + timewords.frequencies(set_aside_hz))
    return s


def search(res: Residual) -> tuple[Located, ...]:
    """Every narrowband line in the calibrated residual, strongest first (empty when none
    passes the local-level test)."""
    if len(res) < MIN_SAMPLES:
        return ()
    ok = np.isfinite(res.r_ut) & np.isfinite(res.t_s)
    if ok.sum() < MIN_SAMPLES:
        return ()
    if not ok.all():
        res = replace(res, t_s=res.t_s[ok], m_ut=res.m_ut[ok], channels={k: v[ok] for k, v in res.channels.items()})
    if np.any(np.diff(res.t_s) < 0) or res.t_s[-1] <= res.t_s[0]:
        return ()  # no frequency without a clock that advances
    scan = _scanned(res)
    last = len(scan.lines) - 1
    free = tuple(located(x, res, scan.threshold, scan.set_aside_hz, scan.beyond_cap_hz if i == last else None)
                 for i, x in enumerate(scan.lines))
    return free + channel_structure(scan.channel_lines, res.floor_ut)


def channel_structure(set_aside: list, floor_ut: float) -> tuple[Located, ...]:
    """The candidates set aside as a logged channel's, one remainder per channel: where the
    channel's effect is left in the residual, said as the channel's and not as free lines."""
    out = []
    for name in dict.fromkeys(c.channel for c in set_aside):
        mine = sorted((c for c in set_aside if c.channel == name), key=lambda c: c.frequency_hz)
        freqs = [c.frequency_hz for c in mine]
        top = max(c.amplitude_ut for c in mine)
        summary = (f"structure that follows {name}: lines at " + timewords.frequencies(freqs) + " (up to "
                   f"{top:.2f} µT, {top / floor_ut:.1f}× the recording's floor) sit where {name}'s own spectrum carries "
                   f"lines, and one direction at one phase — {name} reaching the sensor through a lag — accounts for "
                   f"each: {name}'s effect left in the calibrated residual, not claimed as interference lines")
        params = {"channel": name, "frequency_hz": freqs, "amplitude_ut": [c.amplitude_ut for c in mine]}
        evidence = {"channel_line_statistic": [c.channel_stat for c in mine], "one_direction_misfit": [c.misfit for c in mine],
                    "misfit_threshold": tails.chi2_isf(ALPHA, 2), "alpha": ALPHA, "size_over_floor": top / floor_ut}
        out.append(Located(REST, Kind.REMAINDER, summary, {"channel": name, "frequency_hz": freqs}, params, evidence))
    return tuple(out)


def remove(m_ut: np.ndarray, t_s: np.ndarray, channels, found: Located) -> np.ndarray:
    """The raw samples with the located line subtracted from each axis (the fitted sinusoid,
    phase referred to ``t_ref_s``). The calibration refitted on them is the sensor's own, the
    same at every time of the recording: the interference it carried is gone."""
    m = np.asarray(m_ut, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3 or len(t) != len(m):
        raise ValueError(f"m_ut must be (n, 3) with one time each; got {m.shape} and {t.shape}")
    p = found.params
    ph = 2 * np.pi * float(p["frequency_hz"]) * (t - float(p["t_ref_s"]))
    wave = np.outer(np.cos(ph), p["cos_ut"]) + np.outer(np.sin(ph), p["sin_ut"])
    return m - wave


EFFECT = Effect(NAME, Kind.PHYSICS, search, remove)
