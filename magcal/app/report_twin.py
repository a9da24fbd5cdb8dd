"""The twin panels of the diagnosis report: real against twin, over time, over directions, and
the statistic table (baseline → each effect added → final), written beside the report page.

``write_twin_panels(report, directory)`` writes ``twin_time.png``, ``twin_directions.png`` and
``twin.html`` and links the latter from ``index.html`` when that page is there.
"""

from __future__ import annotations

import html
import os
from pathlib import Path

import numpy as np

from ..diagnose.twin import stats as ts
from ..recordings.atomic import save_figure, write_text
from ..diagnose.twin.text import step_label

_REAL = "#1f5fbf"
_TWIN = "#e07b00"
_BAND = "#f3c48a"
_BAD = "#d62728"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _thin(n: int, most: int = 20000) -> np.ndarray:
    return np.arange(n) if n <= most else np.linspace(0, n - 1, most).astype(int)


def time_figure(final, path: Path) -> str:
    """Residual over time: the recording, one twin, and the block means against the twins' band."""
    plt = _plt()
    real, twin, loc = final.real, final.twin, final.located
    fig, axes = plt.subplots(3, 1, figsize=(11, 7.5), sharex=True)
    lim = np.percentile(np.abs(np.concatenate([real.e, twin.e])), 99.5) * 1.1
    for ax, r, label, colour in ((axes[0], real, "recording", _REAL), (axes[1], twin, "one twin draw", _TWIN)):
        i = _thin(len(r.e))
        ax.plot(r.t[i], r.e[i], lw=0.4, color=colour)
        ax.set_ylim(-lim, lim)
        ax.set_ylabel("|h| − r (µT)")
        ax.set_title(f"radial residual, {label}", loc="left", fontsize=10)
    edges = np.array_split(real.t, ts.N_BLOCKS)
    mids = np.array([0.5 * (p[0] + p[-1]) for p in edges if len(p)])[: len(loc.get("blocks_real", []))]
    ax = axes[2]
    if "blocks_low" in loc:
        k = len(loc["blocks_low"])
        ax.fill_between(mids[:k], loc["blocks_low"], loc["blocks_high"], color=_BAND, step="mid", label="twins 2.5–97.5 %")
    rb = np.asarray(loc["blocks_real"])[: len(mids)]
    bad = np.zeros(len(rb), bool)
    bad[[i for i in loc.get("blocks_outside", []) if i < len(rb)]] = True
    ax.plot(mids, rb, "o-", color=_REAL, ms=4, label="recording")
    ax.plot(mids[bad], rb[bad], "o", color=_BAD, ms=7, label="outside the band")
    ax.set_ylabel("block mean (µT)")
    ax.set_xlabel("t (s)")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title("residual level per time block", loc="left", fontsize=10)
    fig.suptitle(f"Recording against its twin over time (model: {final.step})")
    fig.tight_layout()
    return _save(fig, path, plt)


def _az_el(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.degrees(np.arctan2(u[:, 1], u[:, 0])), np.degrees(np.arcsin(np.clip(u[:, 2], -1, 1)))


def direction_figure(final, path: Path) -> str:
    """Residual over field directions: recording and twin maps, and the cell means."""
    plt = _plt()
    real, twin, loc = final.real, final.twin, final.located
    fig = plt.figure(figsize=(11, 7.5))
    lim = np.percentile(np.abs(real.e), 98)
    for k, (r, label) in enumerate(((real, "recording"), (twin, "one twin draw"))):
        ax = fig.add_subplot(2, 2, k + 1)
        i = _thin(len(r.e), 8000)
        az, el = _az_el(r.u[i])
        sc = ax.scatter(az, el, c=r.e[i], s=3, cmap="coolwarm", vmin=-lim, vmax=lim)
        ax.set_xlim(-180, 180)
        ax.set_ylim(-90, 90)
        ax.set_xlabel("azimuth (°, sensor frame)")
        ax.set_ylabel("elevation (°)")
        ax.set_title(f"|h| − r over directions, {label}", loc="left", fontsize=10)
        fig.colorbar(sc, ax=ax, label="µT")
    ax = fig.add_subplot(2, 1, 2)
    cells = np.asarray(loc["cells_real"])
    x = np.arange(len(cells))
    if "cells_low" in loc:
        ax.bar(x, np.asarray(loc["cells_high"]) - np.asarray(loc["cells_low"]), bottom=loc["cells_low"],
               color=_BAND, width=0.7, label="twins 2.5–97.5 %")
    bad = np.zeros(len(cells), bool)
    bad[loc.get("cells_outside", [])] = True
    ax.plot(x, cells, "o", color=_REAL, label="recording")
    ax.plot(x[bad], cells[bad], "o", color=_BAD, ms=8, label="outside the band")
    ax.set_xticks(x)
    from ..diagnose.twin.names import direction_words

    ax.set_xticklabels([direction_words([i]) for i in x], rotation=60, fontsize=7)
    ends = np.concatenate([cells, loc.get("cells_low", []), loc.get("cells_high", [])]).astype(float)
    ends = ends[np.isfinite(ends)]
    if len(ends):  # a band's end is not the axis's edge: a margin past the lowest and the highest
        pad = 0.05 * max(float(np.ptp(ends)), 1e-9)
        ax.set_ylim(float(ends.min()) - pad, float(ends.max()) + pad)
    ax.set_ylabel("mean residual (µT)")
    ax.set_title("mean residual per direction cell (empty cells: fewer than 10 samples)", loc="left", fontsize=10)
    ax.legend(fontsize=8)
    fig.suptitle(f"Recording against its twin over directions (model: {final.step})")
    fig.tight_layout()
    return _save(fig, path, plt)


def _save(fig, path: Path, plt) -> str:
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return os.path.basename(path)


def table_html(d: dict) -> str:
    """Statistics down, steps across: the recording's value, ✓ inside its twins' band, ✗ not."""
    steps = d["steps"]
    names = [n for n in steps[-1]["bands"] if n not in constant_statistics(d)]
    head = "".join(f"<th>{html.escape(step_label(steps, s))}</th>" for s in steps)
    rows = []
    for n in names:
        cells = []
        for s in steps:
            b = s["bands"].get(n)
            if b is None:
                cells.append("<td></td>")
                continue
            ok = b["inside"]
            tip = f"twins {_fmt(b['twin_low'])} – {_fmt(b['twin_high'])}"
            cells.append(f'<td title="{tip}" style="background:{"#d8f0d8" if ok else "#f6d0d0"}">'
                         f'{"✓" if ok else "✗"} {_fmt(b["real"])}<br><small>{tip}</small></td>')
        rows.append(f"<tr><th>{html.escape(n)}</th>{''.join(cells)}</tr>")
    total = "".join(f"<td><b>{s['inside']}/{s['statistics']}</b></td>" for s in steps)
    return (f"<table border=1 cellspacing=0><tr><th>statistic</th>{head}</tr>{''.join(rows)}"
            f"<tr><th>inside the band</th>{total}</tr></table>")


def constant_statistics(d: dict) -> list[str]:
    """Statistics that cannot tell anything: the recording and every twin give the same value
    at every step (a channel that stays constant through the recording, no jumps anywhere)."""
    out = []
    for n in d["steps"][-1]["bands"]:
        bands = [s["bands"][n] for s in d["steps"] if n in s["bands"]]
        if all(b["real"] == b["twin_low"] == b["twin_high"] for b in bands):
            out.append(n)
    return out


def headline(d: dict) -> str:
    """One sentence: how many statistics the final model's twins hold, against the baseline."""
    first, last = d["steps"][0], d["steps"][-1]
    return (f"<p style=\"font-size:130%\">Final model: <b>{last['inside']} of {last['statistics']}</b> statistics "
            f"of the recording inside its twins' band; baseline (hard iron + white noise): "
            f"{first['inside']} of {first['statistics']}.</p>")


def _fmt(x) -> str:
    return "—" if x is None else f"{x:.3g}"


def _constant_note(d: dict) -> str:
    same = constant_statistics(d)
    if not same:
        return ""
    return (f"<p><small>Not shown (the recording and every twin give the same value at every step, so it "
            f"cannot tell them apart — e.g. a channel that stays constant): "
            f"{html.escape(', '.join(same))}.</small></p>")


def write_twin_panels(report, directory) -> Path:
    """Write the twin figures and page into ``directory``; link them from index.html."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    final = report.final
    figs = [time_figure(final, out / "twin_time.png"), direction_figure(final, out / "twin_directions.png")]
    d = report.to_dict()
    mism = "".join(f"<li><b>{html.escape(m['statistic'])}</b> ({html.escape(m['effect'])}) — {html.escape(m['summary'])}</li>"
                   for m in d["steps"][-1]["mismatches"]) or "<li>none: every statistic of the recording lies in its twins' band</li>"
    imgs = "".join(f'<figure><img src="{f}" style="max-width:100%"></figure>' for f in figs)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>magcal — recording against its twin</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}} td,th{{padding:3px 8px;text-align:center}}</style>
</head><body><h1>The recording against its twin</h1>
<p>{d['draws']} twins per step, each on the recording's own times, channels and field directions,
refitted like the recording. ✓: the recording's statistic lies in its twins' {d['band_pct'][0]}–{d['band_pct'][1]} % band.</p>
{headline(d)}
{table_html(d)}{_constant_note(d)}
<h2>What the final model still misses</h2><ul>{mism}</ul>
{imgs}</body></html>
"""
    write_text(out / "twin.html", page)
    index = out / "index.html"
    if index.exists():
        text = index.read_text(encoding="utf-8")
        link = '<p><a href="twin.html">The recording against its twin (statistics, time, directions)</a></p>'
        if link not in text:
            write_text(index, text.replace("</body>", link + "\n</body>"))
    return out / "twin.html"
