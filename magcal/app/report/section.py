"""The parts a report page is made of: figures with their captions, and sections of figures.

A caption has two halves, so a reader knows why a picture is there before looking at it:
``look_for`` (what the picture would show if something were wrong) and ``found`` (what it
shows for this recording, in numbers).
"""

from __future__ import annotations

import os
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

from ...recordings.atomic import save_figure

# colour-blind-safe colours (Okabe & Ito), one meaning each on every figure of the page
RAW = "#7f7f7f"  # as recorded
BEFORE = "#E69F00"  # the sphere (hard iron only): dots
BEFORE_LINE = "#7a4a00"  # … its running mean
AFTER = "#56B4E9"  # the final model: dots
AFTER_LINE = "#00406e"  # … its running mean
BAD = "#D55E00"  # set aside as glitches, or a finding
GOOD = "#009E73"


@dataclass(frozen=True)
class Figure:
    """One picture on the page: ``file`` in the report's folder, with its caption."""

    file: str
    title: str
    look_for: str
    found: str
    alt: str = ""


@dataclass(frozen=True)
class Section:
    """A titled part of the page: an introduction (``html``, made by magcal, data escaped)
    and figures. ``key`` is its anchor (``index.html#key``)."""

    title: str
    figures: tuple[Figure, ...] = ()
    html: str = ""
    key: str = ""
    extra: dict = field(default_factory=dict)


def wrap(text: str, width: int) -> str:
    """A title broken into lines of at most ``width`` characters (matplotlib does not wrap)."""
    return "\n".join(textwrap.wrap(text, width)) or text


def save(fig, directory, name: str, plt) -> str:
    """Write ``fig`` as ``directory/name.png`` and close it; the file name. Every text on the
    figure must lie inside it (a clipped title is refused here, not found by a reader): the
    check reads the layout savefig made for the file, before the file is written."""

    def inside(figure) -> None:
        problems = clipped_texts(figure)
        if problems:
            raise ValueError(f"{name}: text outside the figure: {problems}")

    path = Path(directory) / f"{name}.png"
    try:
        save_figure(fig, path, check=inside, dpi=100)
    finally:
        plt.close(fig)
    return os.path.basename(path)


def clipped_texts(fig) -> list[str]:
    """What of ``fig`` (its axes with their titles, labels and tick labels, its legends and
    title) is drawn outside its canvas (after a draw); a name for each."""
    renderer = fig.canvas.get_renderer()
    w, h = fig.canvas.get_width_height()

    def outside(bb) -> bool:
        return bb is not None and (bb.x0 < -1 or bb.y0 < -1 or bb.x1 > w + 1 or bb.y1 > h + 1)

    out = [f"axes {ax.get_title()[:40]!r}" for ax in fig.axes
           if ax.get_visible() and outside(ax.get_tightbbox(renderer))]
    for artist in list(fig.legends) + [t for t in fig.texts if t.get_text().strip()]:
        if outside(artist.get_window_extent(renderer)):
            out.append(type(artist).__name__)
    return out
