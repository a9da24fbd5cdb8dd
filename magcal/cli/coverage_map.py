"""The directions a calibration has seen, as a map for the terminal, and where to turn next.

The map is the coverage grid itself (``magcal.fit.coverage``): ``bands`` equal-area zones of the
field's z component (+Z at the top) by ``sectors`` longitudes (−X, −Y, +X, +Y, −X from left to
right), so every cell is the same share of the sphere. A full cell holds as many samples as the
fit keeps per direction; the marker is where the field points now. Pure: counts in, text out.

The field comes in along one direction of the sensor frame, so to fill a cell the board must be
turned until that side of it points along the Earth's field (magnetic north, dipping down in the
northern hemisphere, up in the southern). ``hint`` names that side and how far to turn.
"""

from __future__ import annotations

import numpy as np

from ..fit.coverage import cell_centres, nearest_empty_cell, side_name

FULL, EMPTY, HERE, NEXT = "██", "··", "◆◆", "◎◎"
SHADES = ("░░", "▒▒", "▓▓")
LEGEND = "██ full  ▓▓ ▒▒ ░░ partly (most to least)  ·· none  ◆◆ field now  ◎◎ next"
_GREEN, _YELLOW, _DIM, _CYAN, _RESET = "\033[32m", "\033[33m", "\033[2m", "\033[1;36m", "\033[0m"


def cell_of(direction, bands: int, sectors: int) -> int:
    from ..fit.coverage import cell_index

    return int(cell_index(np.asarray(direction, dtype=np.float64)[None, :], bands, sectors)[0])


def next_cell(counts, bands: int, sectors: int, direction) -> tuple[int, float] | None:
    """The empty cell nearest to where the field points now, and the turn to it in degrees
    (None when no cell is empty): ``fit.coverage.nearest_empty_cell``."""
    return nearest_empty_cell(counts, bands, sectors, direction)


def hint(counts, bands: int, sectors: int, direction) -> str:
    """One sentence: which side of the board to aim along the field next, and how far."""
    found = next_cell(counts, bands, sectors, direction)
    if found is None:
        return "every direction seen: hold still or keep turning slowly while the fit settles"
    cell, angle = found
    side = side_name(cell_centres(bands, sectors)[cell])
    turn = f", about {angle:.0f}° from now" if np.isfinite(angle) else ""
    return (f"next: aim the board's {side} side along the field (north, dipping down in the north): "
            f"◎◎ on the map{turn}")


def _cell_text(n: int, per_cell: int, colour: bool) -> str:
    if n <= 0:
        text, c = EMPTY, _DIM
    elif n >= per_cell:
        text, c = FULL, _GREEN
    else:
        text, c = SHADES[min(len(SHADES) - 1, (len(SHADES) * n) // per_cell)], _YELLOW
    return f"{c}{text}{_RESET}" if colour else text


def render(counts, per_cell: int, bands: int, sectors: int, direction=None, colour: bool = False) -> str:
    """The map: one text row per band, +Z on top; ◆ where the field points now, ◎ the next
    empty cell to fill (pure)."""
    counts = np.asarray(counts)
    here = cell_of(direction, bands, sectors) if direction is not None else -1
    nxt = next_cell(counts, bands, sectors, direction)
    target = nxt[0] if nxt else -1
    width = 2 * sectors
    axis = [" "] * (width + 2)
    for label, lon in (("−X", -180), ("−Y", -90), ("+X", 0), ("+Y", 90), ("−X", 180)):
        at = min(width, int(round((lon + 180) / 360 * width)))
        axis[at:at + 2] = list(label)
    rows = ["     " + "".join(axis).rstrip()]
    for b in reversed(range(bands)):
        cells = []
        for s in range(sectors):
            k = b * sectors + s
            if k == here:
                cells.append(f"{_CYAN}{HERE}{_RESET}" if colour else HERE)
            elif k == target:
                cells.append(f"{_CYAN}{NEXT}{_RESET}" if colour else NEXT)
            else:
                cells.append(_cell_text(int(counts[k]), per_cell, colour))
        label = "+Z" if b == bands - 1 else ("−Z" if b == 0 else "  ")
        rows.append(f" {label} │" + "".join(cells) + "│")
    return "\n".join(rows)
