"""The report's interactive 3-D point cloud: the samples as recorded and as calibrated, drawn on
a canvas by a few lines of script embedded in the page — nothing is fetched when it is viewed.
Drag to turn, wheel to zoom, boxes to show or hide each set. The calibrated points are coloured
by their radial residual (blue below the fitted field, red above), with a wire sphere of the
fitted radius around the origin; the raw points sit on the offset, squashed shell the
calibration undoes. The canvas says how many points it drew (``data-drawn``)."""

from __future__ import annotations

import html
import json

import numpy as np

from .views import symmetric_limit, thin

MAX_CLOUD = 3000

SCRIPT = r"""
(function () {
  const data = JSON.parse(document.getElementById("cloud-data").textContent);
  const cv = document.getElementById("cloud-canvas");
  const ctx = cv.getContext("2d");
  const show = {raw: true, cal: true};
  let yaw = 0.7, pitch = 0.35, zoom = 1.0, drag = null;
  const extent = Math.max(data.field_ut, ...data.raw.map(p => Math.hypot(p[0], p[1], p[2])));

  function turn(p) {
    const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    const x = p[0] * cy - p[1] * sy, y = p[0] * sy + p[1] * cy, z = p[2];
    return [x, y * cp - z * sp, y * sp + z * cp];  // right, depth, up
  }
  function colour(r) {  // blue (below the field) - grey (on it) - red (above)
    const f = Math.max(-1, Math.min(1, r / data.limit_ut)), g = [160, 160, 160];
    const end = f < 0 ? [30, 80, 220] : [215, 40, 30], a = Math.abs(f);
    return `rgb(${g.map((v, i) => Math.round(v + (end[i] - v) * a)).join(",")})`;
  }
  function line(s, a, b, c, w) {
    const pa = turn(a), pb = turn(b);
    ctx.strokeStyle = c; ctx.lineWidth = w; ctx.beginPath();
    ctx.moveTo(s.cx + s.k * pa[0], s.cy - s.k * pa[2]); ctx.lineTo(s.cx + s.k * pb[0], s.cy - s.k * pb[2]);
    ctx.stroke();
  }
  function wire(s) {
    const r = data.field_ut, n = 48;
    for (let j = -2; j <= 2; j++) {  // circles of latitude
      const z = r * Math.sin(j * Math.PI / 6), q = r * Math.cos(j * Math.PI / 6);
      for (let i = 0; i < n; i++) {
        const a = 2 * Math.PI * i / n, b = 2 * Math.PI * (i + 1) / n;
        line(s, [q * Math.cos(a), q * Math.sin(a), z], [q * Math.cos(b), q * Math.sin(b), z], "#d0d0d0", 1);
      }
    }
    for (let j = 0; j < 6; j++) {  // meridians
      const lon = j * Math.PI / 6;
      for (let i = 0; i < n; i++) {
        const a = Math.PI * i / n - Math.PI / 2, b = Math.PI * (i + 1) / n - Math.PI / 2;
        const p = t => [r * Math.cos(t) * Math.cos(lon), r * Math.cos(t) * Math.sin(lon), r * Math.sin(t)];
        line(s, p(a), p(b), "#d0d0d0", 1);
      }
    }
  }
  function draw() {
    const s = {cx: cv.width / 2, cy: cv.height / 2, k: zoom * Math.min(cv.width, cv.height) / (2.3 * extent)};
    ctx.clearRect(0, 0, cv.width, cv.height);
    wire(s);
    const pts = [];
    if (show.raw) data.raw.forEach(p => pts.push([turn(p), "#8a8a8a"]));
    if (show.cal) data.cal.forEach((p, i) => pts.push([turn(p), colour(data.residual_ut[i])]));
    pts.sort((a, b) => b[0][1] - a[0][1]);  // far ones first
    pts.forEach(([q, c]) => { ctx.fillStyle = c; ctx.fillRect(s.cx + s.k * q[0] - 1.5, s.cy - s.k * q[2] - 1.5, 3, 3); });
    [[[1, 0, 0], "#c0392b", "X"], [[0, 1, 0], "#1e8449", "Y"], [[0, 0, 1], "#1f4e9c", "Z"]].forEach(([d, c, name]) => {
      const e = d.map(v => v * extent * 1.05);
      line(s, [0, 0, 0], e, c, 2);
      const q = turn(e);
      ctx.fillStyle = c; ctx.font = "bold 14px sans-serif";
      ctx.fillText("+" + name, s.cx + s.k * q[0] + 4, s.cy - s.k * q[2] - 4);
    });
    cv.dataset.drawn = String(pts.length);
  }
  cv.addEventListener("mousedown", e => { drag = [e.clientX, e.clientY]; });
  window.addEventListener("mouseup", () => { drag = null; });
  window.addEventListener("mousemove", e => {
    if (!drag) return;
    yaw += (e.clientX - drag[0]) * 0.01;
    pitch = Math.max(-1.5, Math.min(1.5, pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY];
    draw();
  });
  cv.addEventListener("wheel", e => { e.preventDefault(); zoom *= Math.exp(-e.deltaY * 0.001); draw(); },
                      {passive: false});
  document.querySelectorAll("input[data-cloud]").forEach(box => box.addEventListener("change", () => {
    show[box.dataset.cloud] = box.checked; draw();
  }));
  draw();
})();
"""


def cloud_data(diagnosis, v) -> dict:
    """The points the cloud draws (at most ``MAX_CLOUD`` of each set, spread over the recording)."""
    sel = v.idx[v.good[v.idx]]
    sel = sel[thin(len(sel), MAX_CLOUD)]
    raw = diagnosis.series.field_ut[sel]
    return {
        "field_ut": round(float(v.field_ut), 3),
        "limit_ut": round(symmetric_limit(v.after[v.good], q=99), 3),
        "raw": np.round(raw, 2).tolist(),
        "cal": np.round(v.h[sel], 2).tolist(),
        "residual_ut": np.round(v.after[sel], 3).tolist(),
    }


def cloud_html(diagnosis, v) -> str:
    """The section's body: the canvas, its switches, the data and the script (all inline)."""
    data = json.dumps(cloud_data(diagnosis, v), separators=(",", ":")).replace("</", "<\\/")
    n = len(json.loads(data)["cal"])
    b = diagnosis.final.offset_ut
    g = v.good
    found = (f"the raw shell is centred at ({b[0]:.1f}, {b[1]:.1f}, {b[2]:.1f}) µT, {float(np.linalg.norm(b)):.1f} µT "
             f"from the origin; the calibrated samples lie {float(np.sqrt(np.mean(v.after[g] ** 2))):.3f} µT RMS "
             f"from the sphere of {v.field_ut:.2f} µT.")
    return (
        f'<p class="how">{n} samples of each set, spread over the recording. Drag to turn, use the '
        'wheel to zoom. <label><input type="checkbox" data-cloud="raw" checked> as recorded (grey)</label> '
        '<label><input type="checkbox" data-cloud="cal" checked> calibrated (coloured by residual)</label></p>'
        '<canvas id="cloud-canvas" width="900" height="620" aria-label="3-D point cloud of the samples"></canvas>'
        f'<p class="caption"><b>Look for:</b> the grey points on a shell off the origin (the hard iron) '
        f'and squashed (soft iron); the calibrated ones on the wire sphere of radius '
        f'{html.escape(f"{v.field_ut:.2f}")} µT around the origin, red and blue mixed '
        f'evenly. A red or blue cap is a direction the model does not fit.<br><b>Found:</b> '
        f'{html.escape(found)}</p>'
        f'<script type="application/json" id="cloud-data">{data}</script>'
        f"<script>{SCRIPT}</script>"
    )
