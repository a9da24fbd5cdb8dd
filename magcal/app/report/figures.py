"""The report's figures, one function each: draw, save, and say in the caption what to look for
and what this recording shows. Each takes the diagnosis, its ``Views``, pyplot and the folder."""

from __future__ import annotations

import numpy as np

from ...diagnose import channels as ch
from ...fit.coverage import DEFAULT_BANDS, DEFAULT_SECTORS, cell_centres, cell_index, side_name
from .section import AFTER, AFTER_LINE, BAD, BEFORE, BEFORE_LINE, RAW, Figure, save, wrap
from .views import binned, running_mean, symmetric_limit, thin

AZIMUTH = "azimuth of the field in the sensor frame (°): 0 = +X, 90 = +Y, ±180 = −X"
ELEVATION = "z of the field's direction (+1 = +Z)"


def _equal_area_axes(ax) -> None:
    ax.set_xlim(-180, 180)
    ax.set_ylim(-1, 1)
    ax.set_xticks([-180, -90, 0, 90, 180], ["−X", "−Y", "+X", "+Y", "−X"])
    ax.set_yticks([-1, -0.5, 0, 0.5, 1], ["−Z", "−0.5", "0", "0.5", "+Z"])
    ax.set_xlabel(AZIMUTH)
    ax.set_ylabel(ELEVATION)


def coverage(diagnosis, v, plt, out) -> Figure:
    """Where the field pointed: the gates' equal-area cells shaded by their samples, the
    samples' directions as dots, the empty cells hatched."""
    az = np.degrees(np.arctan2(v.u[:, 1], v.u[:, 0]))
    ze = np.linspace(-1, 1, DEFAULT_BANDS + 1)
    ae = np.linspace(-180, 180, DEFAULT_SECTORS + 1)
    counts, _, _ = np.histogram2d(v.u[:, 2], az, bins=(ze, ae))
    fig, ax = plt.subplots(figsize=(10, 4.6), constrained_layout=True)
    mesh = ax.pcolormesh(ae, ze, np.ma.masked_equal(counts, 0), cmap="Blues", edgecolors="white", linewidth=1.0,
                         norm=plt.matplotlib.colors.LogNorm(vmin=1, vmax=max(float(counts.max()), 10.0)))
    for i, j in zip(*np.nonzero(counts == 0)):
        ax.add_patch(plt.Rectangle((ae[j], ze[i]), ae[j + 1] - ae[j], ze[i + 1] - ze[i], facecolor="#f6d5cc",
                                   edgecolor="white", hatch="///", linewidth=1.0))
    sel = v.idx[:: max(1, len(v.idx) // 4000)]
    ax.plot(az[sel], v.u[sel, 2], ".", ms=1.5, color="#222222", alpha=0.5)
    _equal_area_axes(ax)
    fig.colorbar(mesh, ax=ax, label="samples in the cell (log scale)")
    cells = np.bincount(cell_index(v.u), minlength=DEFAULT_BANDS * DEFAULT_SECTORS)
    empty = np.flatnonzero(cells == 0)
    share = 1 - len(empty) / len(cells)
    ax.set_title(wrap(f"Directions seen: {len(cells) - len(empty)} of {len(cells)} equal-area cells "
                      f"({100 * share:.0f} %)", 90))
    name = save(fig, out, "coverage", plt)
    if len(empty):
        sides = [side_name(c).split("/")[0] for c in cell_centres()[empty]]
        worst = max(set(sides), key=sides.count)
        gap = (f"{len(empty)} cells were never seen, most of them ({sides.count(worst)}) where the board's "
               f"{worst} side points along the field")
    else:
        gap = "every cell holds samples"
    return Figure(name, "Which directions the recording covers",
                  "red hatched cells: directions the field never came from (each cell is the same "
                  "share of the sphere). A calibration is only tested where there are samples; soft "
                  "iron needs most of the sphere.",
                  f"{100 * share:.0f} % of the 128 equal-area cells the calibration gates use hold "
                  f"samples; {gap}.", "map of the field directions seen")


def magnitude(diagnosis, v, plt, out) -> Figure:
    """|B| as recorded, with the sphere's offset, and with the final model."""
    g = v.good
    fig, (wide, near) = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True)
    lo, hi = np.percentile(np.concatenate([v.raw_norm[g], v.final_norm[g]]), [0.5, 99.5])
    wide.hist(v.raw_norm[g], bins=80, range=(lo, hi), color=RAW, alpha=0.8, label="as recorded |m|")
    wide.hist(v.final_norm[g], bins=80, range=(lo, hi), color=AFTER_LINE, histtype="step", lw=2,
              label="calibrated")
    wide.set_xlabel("|B| (µT)")
    wide.set_ylabel("samples")
    wide.set_title("As recorded vs calibrated")
    wide.legend(fontsize=9)
    r = v.field_ut
    half = max(5 * float(np.std(v.final_norm[g])), 3 * float(np.std(v.sphere_norm[g])), 0.5)
    rng = (r - half, r + half)
    near.hist(v.sphere_norm[g], bins=60, range=rng, color=BEFORE, alpha=0.75, label="sphere (hard iron only)")
    near.hist(v.final_norm[g], bins=60, range=rng, color=AFTER_LINE, histtype="step", lw=2,
              label=f"final: {diagnosis.model_name(diagnosis.final)}")
    near.axvline(r, color="black", lw=1, ls="--", label=f"fitted field {r:.2f} µT")
    near.set_xlabel("|B| (µT)")
    near.set_title("Close to the fitted field")
    near.legend(fontsize=9)
    name = save(fig, out, "magnitude", plt)
    sd = [float(np.std(x[g])) for x in (v.raw_norm, v.sphere_norm, v.final_norm)]
    return Figure(name, "|B| before and after calibration",
                  "a calibrated field has one magnitude, the Earth's: a narrow peak. A wide or "
                  "double peak after calibration is something the model left out.",
                  f"the spread (standard deviation) of |B| is {sd[0]:.2f} µT as recorded, {sd[1]:.3f} µT "
                  f"with the sphere's offset and {sd[2]:.3f} µT with the final model; the noise alone "
                  f"would give about {diagnosis.noise_ut:.3f} µT.", "histograms of the field magnitude")


def directions(diagnosis, v, plt, out) -> Figure:
    """The radial residual over the field directions, before and after."""
    az = np.degrees(np.arctan2(v.u[:, 1], v.u[:, 0]))
    sel = v.idx[v.good[v.idx]]
    lim = symmetric_limit(v.before[v.good], q=99)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), sharey=True, constrained_layout=True)
    for ax, r, label, rms in ((axes[0], v.before, "before: sphere (hard iron only)", diagnosis.baseline.rms_ut),
                              (axes[1], v.after, f"after: {diagnosis.model_name(diagnosis.final)}",
                               diagnosis.final.rms_ut)):
        sc = ax.scatter(az[sel], v.u[sel, 2], c=r[sel], cmap="RdBu_r", vmin=-lim, vmax=lim, s=5, linewidths=0)
        ax.set_title(wrap(f"{label}, RMS {rms:.3f} µT", 60))
        _equal_area_axes(ax)
    axes[1].set_ylabel("")
    fig.colorbar(sc, ax=axes, label="radial residual |B| − r (µT)")
    name = save(fig, out, "directions", plt)
    soft = [f for f in diagnosis.findings if f.effect == "soft_iron"]
    found = (f"soft iron found: {soft[0].summary.rstrip('.')}" if soft
             else "no soft iron was found; the colours before and after differ by what the other terms explain")
    return Figure(name, "Residual over the directions the sensor saw",
                  "red and blue patches that follow the direction (e.g. opposite sides alike): a "
                  "direction-dependent term the sphere leaves out, soft iron. Noise is a fine speckle.",
                  f"RMS {diagnosis.baseline.rms_ut:.3f} µT before, {diagnosis.final.rms_ut:.3f} µT after; {found}.",
                  "residual by direction, before and after")


def over_time(diagnosis, v, plt, out) -> Figure:
    """The radial residual against time, with running means and the held-out blocks."""
    g, idx = v.good, v.idx
    fig, ax = plt.subplots(figsize=(13, 4.4), constrained_layout=True)
    ax.plot(v.t[idx], v.before[idx], ".", ms=2, color=BEFORE, alpha=0.35, label="before (sphere)")
    ax.plot(v.t[idx[g[idx]]], v.after[idx[g[idx]]], ".", ms=2, color=AFTER, alpha=0.35,
            label=f"after ({diagnosis.model_name(diagnosis.final)})")
    cb, mb = running_mean(v.t[g], v.before[g])
    ca, ma = running_mean(v.t[g], v.after[g])
    ax.plot(cb, mb, "-", color=BEFORE_LINE, lw=2.2, label="running mean, before")
    ax.plot(ca, ma, "-", color=AFTER_LINE, lw=2.2, label="running mean, after")
    lim = symmetric_limit(v.before[g], v.after[g]) * 1.15
    bad = ~g
    if bad.any():
        ax.plot(v.t[bad], np.clip(v.before[bad], -lim, lim), "x", color=BAD, ms=6,
                label=f"{int(bad.sum())} glitch(es) set aside (clipped to the frame)")
    for a, _ in diagnosis.folds[1:]:
        ax.axvline(v.t[min(a, len(v.t) - 1)], color="0.75", lw=0.8, ls=":", zorder=0)
    _mark_located(ax, diagnosis, v)
    ax.set_ylim(-lim, lim)
    ax.set_xlim(v.t[0], v.t[-1])
    ax.set_xlabel(f"{v.t_axis}; dotted lines: the held-out blocks")
    ax.set_ylabel("radial residual |B| − r (µT)")
    ax.set_title("Residual against time")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=5, fontsize=9, markerscale=4, frameon=False)
    name = save(fig, out, "time", plt)
    swing_b, swing_a = (float(np.ptp(m)) if len(m) else 0.0 for m in (mb, ma))
    return Figure(name, "Residual against time",
                  "a running mean that drifts or steps: an offset that changes while recording "
                  "(temperature, a current, a magnetised part); after a good model it stays flat at 0.",
                  f"the running mean swings over {swing_b:.2f} µT before and {swing_a:.2f} µT after, over "
                  + (f"{v.t[-1]:.1f} {v.t_unit}." if v.clock else f"{len(v.t)} samples (the recording has no time)."),
                  "residual against time")


def _mark_located(ax, diagnosis, v) -> None:
    """Every finding's and limit's ``where.time_s`` on the time axis: an instant (a change point,
    a jump) as a dashed line, a stretch as a shaded band — where the terminal and the JSON say."""
    t0 = float(diagnosis.series.t_s[0]) if len(v.t) else 0.0  # v.t is time since the first sample, like the axis
    label = "located in time (a finding or a limit)"
    for item in (*diagnosis.findings, *diagnosis.limits):
        for x in (item.where or {}).get("time_s", ()):
            a, b = (np.resize(np.asarray(x, float), 2) - t0) / v.t_scale_s
            (ax.axvline(a, color=BAD, lw=1.2, ls="--", label=label) if a == b else
             ax.axvspan(a, b, color=BAD, alpha=0.12, lw=0, label=label))
            label = None


def _panel_name(c: str, v) -> str:
    """What a panel calls its channel: time is the sample index when the recording has none
    (its t_s counts samples), as the terminal says it ("no time column: sample index")."""
    return "sample index" if c == ch.TIME and not v.clock else c


def _channel_panel(ax, diagnosis, v, c: str, found: dict) -> str:
    """One channel's panel: the offset left along its term, without and with it. Its verdict."""
    x = v.chans[c]
    cands = diagnosis.tests.get("candidates", {})
    k = diagnosis.final.coef_ut_per_unit.get(c)
    ref = diagnosis.final.reference.get(c, 0.0)
    if k is None:
        k = np.asarray(cands.get(ch.effect_name(c), {}).get("coef_ut_per_unit", np.zeros(3)))
        ref = float(np.mean(x)) if c != ch.CURRENT else 0.0
    size = float(np.linalg.norm(k))
    kd = k / size if size > 0 and c in found else _seen_most(v)
    proj = v.u @ kd
    sel = v.good & (np.abs(proj) > 0.7)
    part = v.after + (v.u @ k) * (x - ref)  # the residual with this channel's term put back
    shown = (x - x[0]) / v.t_scale_s if c == ch.TIME else x  # time since the start, not epoch seconds
    xs, yb, ya = shown[sel], part[sel] / proj[sel], v.after[sel] / proj[sel]
    th = thin(len(xs), 5000)
    ax.plot(xs[th], yb[th], ".", ms=2, color=RAW, alpha=0.35)
    cb, mb = binned(xs, yb)
    ca, ma = binned(xs, ya)
    ax.plot(cb, mb, "o-", color=BEFORE_LINE, lw=2, ms=4, label="without this term")
    ax.plot(ca, ma, "o-", color=AFTER_LINE, lw=2, ms=4, label="with the final model")
    ax.axhline(0, color="0.6", lw=0.8, zorder=0)
    spread = max(np.nanmax(np.abs(mb)) if len(mb) else 0.0, 3 * diagnosis.noise_ut / np.sqrt(max(len(xs) / 16, 1)),
                 0.2)
    ax.set_ylim(-2.5 * spread, 2.5 * spread)
    if not sel.any():  # the term points where the recording never looked
        ax.text(0.5, 0.5, "no sample looks along this term", transform=ax.transAxes, ha="center", color="0.4")
        if np.ptp(shown) > 0:
            ax.set_xlim(np.min(shown), np.max(shown))
    unit = ch.unit_of(c, v.clock)
    ax.set_xlabel(v.t_axis if c == ch.TIME
                  else f"{c} ({unit})" if unit != "unit" else c)
    ax.set_ylabel("offset along the term (µT)")
    verdict = f"FOUND: {found[c]}, {size:.3g} µT/{unit}" if c in found else "nothing found"
    ax.set_title(wrap(f"{_panel_name(c, v)}: {verdict}", 42), color=BAD if c in found else "black", fontsize=10)
    ax.locator_params(axis="x", nbins=5)
    ax.legend(fontsize=8, loc="upper left")
    return f"{_panel_name(c, v)}: {verdict}"


def _seen_most(v) -> np.ndarray:
    """The direction the recording's field points along most (the mean of its directions): a
    channel without a term in the model is drawn along it, where an offset shows in most
    samples (along a fixed axis, or along a rejected estimate's noisy direction, a drone that
    stays level left its panels empty)."""
    mean = v.u[v.good].mean(axis=0) if v.good.any() else np.zeros(3)
    norm = float(np.linalg.norm(mean))
    return mean / norm if norm > 0.1 else np.array([1.0, 0.0, 0.0])


def channels(diagnosis, v, plt, out) -> Figure:
    """The offset left in the residual against each channel (and time), in a grid."""
    left = {x.channel: x.left_out_because for x in diagnosis.limits if x.left_out}
    names = [c for c in diagnosis.series.channels
             if c not in left and np.all(np.isfinite(diagnosis.series.channels[c]))] + [ch.TIME]
    cols = min(3, len(names))
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.9 * rows), squeeze=False, constrained_layout=True)
    found = {f.params.get("channel"): f.effect for f in diagnosis.findings}
    verdicts = [_channel_panel(ax, diagnosis, v, c, found) for ax, c in zip(axes.flat, names)]
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    name = save(fig, out, "channels", plt)
    hits = [text for c, text in zip(names, verdicts) if c in found]  # a finding's channel, not the words drawn
    found_text = ("; ".join(hits) + f"; nothing in the other {len(names) - len(hits)}." if hits
                  else f"no channel of the {len(names)} ({', '.join(_panel_name(c, v) for c in names)}) "
                  "carries an offset of its own.")
    by_reason: dict = {}
    for c, why in left.items():
        by_reason.setdefault(why, []).append(c)
    not_tested = "".join(f" Not tested, so not drawn: {', '.join(cs)}: {why}." for why, cs in by_reason.items())
    return Figure(name, "Offset against each logged channel",
                  "a brown line (the residual without the channel's term) with a slope: the offset "
                  "follows that channel (a temperature coefficient, a current); the navy line (with the "
                  "final model) flat at 0 once the model includes it. " + (
                      "t_s is time" if v.clock else "The sample index stands for time (the recording has none)")
                  + ": a slope is a drift.",
                  found_text + not_tested, "offset against each channel")


def heldout(diagnosis, v, plt, out) -> Figure:
    """Held-out RMS per contiguous block: each block predicted by a fit without it."""
    fr = np.array(diagnosis.fold_rms) if diagnosis.fold_rms else np.zeros((0, 2))
    k = np.arange(len(fr))
    fig, ax = plt.subplots(figsize=(9, 4.4), constrained_layout=True)
    ax.bar(k - 0.2, fr[:, 0] if len(fr) else [], 0.4, color=BEFORE, label="sphere")
    ax.bar(k + 0.2, fr[:, 1] if len(fr) else [], 0.4, color=AFTER_LINE, label="final model")
    if np.isfinite(diagnosis.simulated_rms_ut):
        ax.axhline(diagnosis.simulated_rms_ut, color="black", ls="--", lw=1, label="the noise floor the model predicts")
    labels = []
    for i, (a, b) in enumerate(diagnosis.folds):
        t0, t1 = v.t[min(a, len(v.t) - 1)], v.t[min(b, len(v.t)) - 1]
        labels.append(f"block {i + 1}\n{t0:.0f}–{t1:.0f} {v.t_unit}")
    ax.set_xticks(k, labels[: len(k)])
    ax.set_ylabel("held-out radial RMS (µT)")
    ax.set_ylim(0, max(float(fr.max()) if len(fr) else 1.0, diagnosis.simulated_rms_ut
                       if np.isfinite(diagnosis.simulated_rms_ut) else 0.0) * 1.15)
    ax.set_title("Each block predicted by a fit that never saw it")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=3, fontsize=9, frameon=False)
    name = save(fig, out, "heldout", plt)
    better = int(np.sum(fr[:, 1] < fr[:, 0])) if len(fr) else 0
    return Figure(name, "Held-out blocks: does the model predict data it never saw?",
                  "the final model's bars lower than the sphere's in every block and near the dashed noise "
                  "floor; a term that only fits noise would not help on held-out blocks.",
                  f"held-out RMS {diagnosis.baseline_heldout_rms_ut:.3f} µT with the sphere, "
                  f"{diagnosis.final_heldout_rms_ut:.3f} µT with the final model, lower in {better} of {len(fr)} "
                  "blocks.", "held-out RMS per block")


ALL = (coverage, magnitude, directions, over_time, channels, heldout)
