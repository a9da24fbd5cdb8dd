"""The diagnosis as a page a person can read: ``write_report(diagnosis, directory)``.

``directory/index.html`` opens with the calibration (offset, field, soft iron, the terms found,
each with its 1σ), then what was found and what the recording could not test, then one figure
per question — which directions were seen (``coverage.png``), |B| before and after
(``magnitude.png``), the residual over directions (``directions.png``) and over time
(``time.png``), against each logged channel (``channels.png``, a grid), on held-out blocks
(``heldout.png``) — each captioned with what to look for and what this recording shows, and an
interactive 3-D point cloud drawn by a script inside the page. Nothing is fetched when the page
is viewed. Needs matplotlib (the ``report`` extra).

More sections — the sensor twin's, say — are added with ``sections=``: each item is a
``Section`` (title, figures, an HTML introduction) or a function ``(diagnosis, directory, plt)
-> Section | None`` that draws its own figures into the folder (``save`` writes one and checks
that no text is clipped; ``Figure`` carries its caption). They follow the built-in sections, in
the order given, and get a link at the top of the page.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ...core.errors import InputError
from ...recordings.atomic import write_text
from . import figures
from .cloud import cloud_html
from .page import calibration_table, esc, findings_html, page, page_html
from .section import Figure, Section, save, wrap
from .views import Views, views_of

__all__ = ["Figure", "Section", "Views", "save", "views_of", "wrap", "write_log_report", "write_report"]


def _plt():
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - the report extra is installed in tests
        raise InputError("--report needs matplotlib: pip install 'magcal-mpu9150[report]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 10, "axes.titlesize": 12, "axes.titleweight": "bold",
                         "axes.spines.top": False, "axes.spines.right": False})
    return plt


def builtin_sections(diagnosis, out: Path, plt, result: dict | None = None) -> list[Section]:
    v = views_of(diagnosis)
    draw = {f.__name__: f(diagnosis, v, plt, out) for f in figures.ALL}
    draw["channels"] = _log_terms_said(draw["channels"], result)
    return [
        Section("The calibration", html=calibration_table(diagnosis, result), key="calibration"),
        Section("What was found", html=findings_html(diagnosis.to_dict(), result), key="findings"),
        Section("Coverage and magnitude", (draw["coverage"], draw["magnitude"]), key="coverage"),
        Section("Where the model and the data disagree", (draw["directions"], draw["over_time"], draw["channels"]),
                key="residuals"),
        Section("Held-out test", (draw["heldout"],), key="heldout"),
        Section("The samples in 3-D", html=cloud_html(diagnosis, v), key="cloud"),
    ]


def _log_terms_said(fig: Figure, result: dict | None) -> Figure:
    """On a flight log, the channel panels are |m| alone's: their caption names the terms the fit
    against the expected field kept, which |m| cannot see on a flight."""
    kept = [t["channel"] for t in ((result or {}).get("flight_log") or {}).get("terms", []) if t.get("kept")]
    if not kept:
        return fig
    return replace(fig, found=f"From |m| alone: {fig.found} Against the expected field, the flight-log fit keeps "
                              f"{', '.join(kept)} (its section below): terms |m| cannot test on a flight, where the "
                              "board turns while they change.")


def write_report(diagnosis, directory, title: str = "recording", sections=(), result: dict | None = None) -> Path:
    """Draw the figures into ``directory`` and write ``index.html``; its path. ``result``: the
    command's JSON (``magcal diagnose --json``), whose calibration the page shows — on a flight
    log, the flight-log fit's — so that the page, the text and the JSON carry the same numbers."""
    plt = _plt()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    parts = builtin_sections(diagnosis, out, plt, result)
    for extra in sections:
        made = extra(diagnosis, out, plt) if callable(extra) else extra
        if made is not None:
            parts.append(made)
    path = out / "index.html"
    write_text(path, page(diagnosis, title, parts))
    return path


def write_log_report(result: dict, traces: dict | None, directory, title: str = "flight log") -> Path:
    """The page of a flight log whose |m| alone could not be diagnosed (a mostly level flight):
    the calibration the result holds — the flight-log fit's — and that fit's terms and figure."""
    from .flightlog import flight_log_section

    plt = _plt()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    found = (f"<p>|m| alone was not diagnosed: {esc(result.get('magnitude_failure', ''))}</p>"
             + findings_html({"findings": [], "limits": []}, result))
    parts = [Section("The calibration", html=calibration_table(None, result), key="calibration"),
             Section("What was found", html=found, key="findings"),
             flight_log_section(result, traces)(None, out, plt)]
    sub = f"{result.get('n_samples', 0)} samples. Read as: {esc(str(result.get('input', title)))}."
    path = out / "index.html"
    write_text(path, page_html(title, sub, parts))
    return path
