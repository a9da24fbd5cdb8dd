"""The diagnosis as pictures: what was wrong, where, and how the fix does on unseen data.

``write_report(diagnosis, directory)`` writes ``sphere.png`` (radial residual over the field
directions, before/after), ``time.png`` (residual against time), ``channels.png`` (residual
against each auxiliary channel), ``heldout.png`` (held-out RMS per contiguous block) and an
``index.html`` page tying them to the findings. Needs matplotlib (the ``report`` extra).
"""

from __future__ import annotations

import html
import os
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..diagnose import channels as ch

_MAX_POINTS = 20000
_BEFORE = "#9a9a9a"
_AFTER = "#1f5fbf"
_BAD = "#d62728"


def _plt():
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - the report extra is installed in tests
        raise InputError("--report needs matplotlib: pip install 'magcal-mpu9150[report]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def residuals(diagnosis) -> tuple[np.ndarray, np.ndarray, dict]:
    """Radial residual of the baseline and the final model on every analysed sample."""
    s = diagnosis.series
    chans = dict(s.channels)
    chans[ch.TIME] = s.t_s
    before = diagnosis.baseline.residual(s.field_ut, {})
    after = diagnosis.final.residual(s.field_ut, chans)
    return before, after, chans


def _thin(n: int) -> np.ndarray:
    return np.arange(n) if n <= _MAX_POINTS else np.linspace(0, n - 1, _MAX_POINTS).astype(int)


def _running(x: np.ndarray, y: np.ndarray, bins: int = 40):
    order = np.argsort(x)
    xs, ys = x[order], y[order]
    edges = np.linspace(0, len(xs), bins + 1).astype(int)
    cx = np.array([xs[a:b].mean() for a, b in zip(edges[:-1], edges[1:]) if b > a])
    cy = np.array([ys[a:b].mean() for a, b in zip(edges[:-1], edges[1:]) if b > a])
    return cx, cy


def _binned(x: np.ndarray, y: np.ndarray, bins: int = 16):
    """Mean of y within equal-count ranges of x (repeated values of an intermittent channel
    share one range)."""
    if len(x) == 0:
        return np.zeros(0), np.zeros(0)
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 5 and np.ptp(x) > 0:  # an on/off channel: equal-width ranges instead
        edges = np.linspace(x.min(), x.max(), 9)
    if len(edges) < 2:
        return np.array([x.mean()]), np.array([y.mean()])
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    cs, ms = [], []
    for b in range(len(edges) - 1):
        sel = which == b
        if sel.sum() >= 5:
            cs.append(x[sel].mean())
            ms.append(y[sel].mean())
    return np.array(cs), np.array(ms)


def write_report(diagnosis, directory, title: str = "recording") -> Path:
    plt = _plt()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    before, after, chans = residuals(diagnosis)
    s = diagnosis.series
    bad = diagnosis.outlier_mask
    good = ~bad
    idx = _thin(len(s))
    lim = float(np.percentile(np.abs(before[good]), 99)) or 1.0
    names = {}

    # -- residual over the sphere of directions --------------------------------------------
    h = diagnosis.final.calibration().correct(s.field_ut, {c: chans[c] for c in diagnosis.final.spec.channels})
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    az = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    sz = u[:, 2]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), sharey=True, constrained_layout=True)
    for ax, r, label, rms in (
        (axes[0], before, "before: sphere (hard iron only)", diagnosis.baseline.rms_ut),
        (axes[1], after, f"after: {diagnosis.model_name(diagnosis.final)}", diagnosis.final.rms_ut),
    ):
        sel = idx[good[idx]]
        sc = ax.scatter(az[sel], sz[sel], c=r[sel], cmap="RdBu_r", vmin=-lim, vmax=lim, s=4, linewidths=0)
        ax.set_title(f"{label}\nRMS {rms:.3f} µT")
        ax.set_xlabel("field azimuth in the sensor frame (deg)")
        ax.set_xlim(-180, 180)
        ax.set_ylim(-1, 1)
    axes[0].set_ylabel("z component of the field direction (equal-area)")
    fig.colorbar(sc, ax=axes, label="radial residual |ĥ| − r (µT)")
    fig.suptitle("Residual over the directions the sensor saw: structure = a missing direction-dependent term")
    names["sphere"] = _save(fig, out / "sphere.png", plt)

    # -- residual against time ----------------------------------------------------------------
    t = s.t_s
    fig, ax = plt.subplots(figsize=(12, 4.2), constrained_layout=True)
    ax.plot(t[idx], before[idx], ".", ms=2, color=_BEFORE, label=f"before (sphere), RMS {diagnosis.baseline.rms_ut:.3f} µT")
    ax.plot(t[idx[good[idx]]], after[idx[good[idx]]], ".", ms=2, color=_AFTER, alpha=0.6,
            label=f"after ({diagnosis.model_name(diagnosis.final)}), RMS {diagnosis.final.rms_ut:.3f} µT")
    for r, col in ((before, _BEFORE), (after, _AFTER)):
        cx, cy = _running(t[good], r[good], 60)
        ax.plot(cx, cy, "-", color="black" if col == _BEFORE else _AFTER, lw=2)
    if bad.any():
        ax.plot(t[bad], np.clip(before[bad], -3 * lim, 3 * lim), "x", color=_BAD, ms=7)
        # the legend scales markers ×4 (for the tiny residual dots): its cross is drawn at 7/4
        ax.plot([], [], "x", color=_BAD, ms=7 / 4, label=f"{int(bad.sum())} glitch(es) set aside")
    for a, b in diagnosis.folds:
        ax.axvline(t[min(a, len(t) - 1)], color="0.85", lw=0.8, zorder=0)
    ax.set_ylim(-3 * lim, 3 * lim)
    ax.set_xlabel("time (s)   — thin vertical lines: the contiguous held-out blocks")
    ax.set_ylabel("radial residual (µT)")
    ax.set_title("Residual against time: a drifting or stepping mean = a time-varying offset (lines: running mean)")
    ax.legend(loc="upper right", fontsize=8, markerscale=4)
    names["time"] = _save(fig, out / "time.png", plt)

    # -- offset against each channel (and time): partial residuals ---------------------------------
    chan_names = [c for c in s.channels if np.all(np.isfinite(s.channels[c]))] + [ch.TIME]
    fig, axes = plt.subplots(1, len(chan_names), figsize=(5.2 * len(chan_names), 4.2), squeeze=False, constrained_layout=True)
    found = {f.params.get("channel"): f.effect for f in diagnosis.findings}
    coefs = diagnosis.final.coef_ut_per_unit
    cands = diagnosis.tests.get("candidates", {})
    for ax, c in zip(axes[0], chan_names):
        x = chans[c]
        ref = diagnosis.final.reference.get(c, 0.0)
        k = coefs.get(c)
        if k is None:
            k = np.asarray(cands.get(ch.effect_name(c), {}).get("coef_ut_per_unit", np.zeros(3)))
            ref = float(np.mean(x)) if c != ch.CURRENT else 0.0
        size = float(np.linalg.norm(k))
        kd = k / size if size > 0 else np.array([1.0, 0.0, 0.0])
        proj = u @ kd
        sel = good & (np.abs(proj) > 0.7)
        part = after + (u @ k) * (x - ref)  # the residual with this channel's term put back
        y_before = part[sel] / proj[sel]
        y_after = after[sel] / proj[sel]
        xs_ = x[sel]
        th = _thin(len(xs_))
        ax.plot(xs_[th], y_before[th], ".", ms=2, color=_BEFORE, alpha=0.4)
        cb, mb = _binned(xs_, y_before)
        ca, ma = _binned(xs_, y_after)
        ax.plot(cb, mb, "o-", color="black", lw=2, label="without this term")
        ax.plot(ca, ma, "o-", color=_AFTER, lw=2, label="with it (final model)" if c in found else "after")
        ax.axhline(0, color="0.8", lw=0.8, zorder=0)
        spread = max(np.nanmax(np.abs(mb)) if len(mb) else 0.0, 3 * diagnosis.noise_ut / np.sqrt(max(len(xs_) / 16, 1)), 0.2)
        ax.set_ylim(-2.5 * spread, 2.5 * spread)
        ax.set_xlabel(c)
        ax.set_ylabel("offset along (" + ", ".join(f"{v:+.2f}" for v in kd) + ") (µT)")
        ax.set_title(
            f"{c}: FOUND {found[c]} ({size:.3g} µT/{ch.unit_of(c)})" if c in found else f"{c}: nothing found",
            color=_BAD if c in found else "black",
        )
        ax.legend(fontsize=8, loc="upper left")
    fig.suptitle("Offset left in the residual against each channel: a slope = an offset that follows it; flat = explained")
    names["channels"] = _save(fig, out / "channels.png", plt)

    # -- held-out comparison ----------------------------------------------------------------------
    fig, ax = plt.subplots(figsize=(8, 4), constrained_layout=True)
    fr = np.array(diagnosis.fold_rms) if diagnosis.fold_rms else np.zeros((0, 2))
    k = np.arange(len(fr))
    ax.bar(k - 0.2, fr[:, 0] if len(fr) else [], 0.4, color=_BEFORE, label=f"sphere: {diagnosis.baseline_heldout_rms_ut:.3f} µT overall")
    ax.bar(k + 0.2, fr[:, 1] if len(fr) else [], 0.4, color=_AFTER, label=f"final: {diagnosis.final_heldout_rms_ut:.3f} µT overall")
    if np.isfinite(diagnosis.simulated_rms_ut):
        ax.axhline(diagnosis.simulated_rms_ut, color="black", ls="--", lw=1, label=f"noise floor the model predicts: {diagnosis.simulated_rms_ut:.3f} µT")
    ax.set_xticks(k, [f"block {i + 1}" for i in k])
    ax.set_ylabel("held-out radial RMS (µT)")
    ax.set_title("Each block fitted without it, then predicted: lower is better")
    ax.legend(fontsize=8, loc="lower right")
    names["heldout"] = _save(fig, out / "heldout.png", plt)

    (out / "index.html").write_text(_html(diagnosis, names, title), encoding="utf-8")
    return out / "index.html"


def _save(fig, path: Path, plt) -> str:
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.path.basename(path)


def _html(diagnosis, names: dict, title: str) -> str:
    d = diagnosis.to_dict()
    esc = html.escape
    rows = "".join(
        f"<li><b>{esc(f['effect'])}</b> — {esc(f['summary'])}</li>" for f in d["findings"]
    ) or (
        "<li>Nothing proven — but see the limits below.</li>"
        if any(x.get("suspected") for x in d.get("limits", []))
        else "<li>Nothing left out: the sphere (hard-iron) model explains the recording to its noise.</li>"
    )
    limits = "".join(f"<li><b>{esc(x['effect'])}</b> — {esc(x['summary'])}</li>" for x in d.get("limits", []))
    if limits:
        limits = f"<h2>Limits: what this recording could not test or pin down</h2><ul>{limits}</ul>"
    src = diagnosis.series.source
    source = f" Read as: {esc(src)}." if src else ""
    b, fi = d["baseline"], d["final"]
    imgs = "".join(
        f'<figure><img src="{esc(v)}" alt="{esc(k)}" style="max-width:100%"></figure>' for k, v in names.items()
    )
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>magcal diagnose — {esc(title)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}} td,th{{padding:2px 12px;text-align:right}}</style>
</head><body>
<h1>What the calibration left out — {esc(title)}</h1>
<p>{d['n_samples']} samples; white-noise level {d['noise_ut']:.3f} µT per axis.{source}</p>
<h2>Findings</h2><ul>{rows}</ul>
{limits}
<h2>Fit, in-sample and on held-out contiguous blocks</h2>
<table><tr><th></th><th>model</th><th>RMS (µT)</th><th>held-out RMS (µT)</th></tr>
<tr><td>before</td><td>{esc(b['model'])}</td><td>{b['rms_ut']:.3f}</td><td>{b['heldout_rms_ut']:.3f}</td></tr>
<tr><td>after</td><td>{esc(fi['model'])}</td><td>{fi['rms_ut']:.3f}</td><td>{fi['heldout_rms_ut']:.3f}</td></tr>
<tr><td>model's own prediction</td><td>simulated with this recording's directions and noise</td><td>{fi['simulated_rms_ut']:.3f}</td><td></td></tr>
</table>
{imgs}
</body></html>
"""
