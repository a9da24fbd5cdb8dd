"""Body-relative guidance while a calibration collects: which side of the board is down, a
checklist of the six sides each turned a full circle while down (as QGroundControl asks for
them), and a nudge when the board has not moved for a few seconds.

The accelerometer of a board at rest reads the reaction to gravity: +1 g along the axis that
points up, so the axis that points down is the one most against it. A side counts as down within
35° of that axis. While it is down, turning the board about the vertical sweeps the field's
horizontal part through the headings; the side is done when ``DONE_BINS`` of the ``HEADING_BINS``
30° headings were seen. Boards that send no accelerometer (firmware before 0.3.0, sim://?accel=off) get only the
stillness nudge; the field-relative hint (``magcal.cli.coverage_map``) stays theirs.

Axes as printed on the boards, which are the IMU's (its accelerometer's): +X to the right, +Y to
the front, +Z up out of the components side. The samples' accelerometer comes in the field's frame,
the magnetometer's (``magcal.devices.protocol_client.accel_aux``); given the chip, the guide names
the side in the IMU's axes (``Chip.mag_to_accel``) and reads headings in the magnetometer's. Pure:
samples in, advice out; times come with the samples, no clock is read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from ..core.chips import Chip

STILL_S = 3.0  # no turn of more than MOVE_DEG for this long: "you are not moving"
MOVE_DEG = 4.0
SIDE_COS = float(np.cos(np.radians(35.0)))  # a side is down within 35° of its axis
HEADING_BINS = 12
DONE_BINS = 10  # 300° of the circle
MIN_HORIZONTAL = 0.2  # the field's horizontal share needed to read a heading


class Side(Enum):
    """A side of the board by the body axis that points down when it lies on it."""

    BOTTOM = ("flat", "flat (components up)", 2, -1)
    TOP = ("upside down", "upside down", 2, +1)
    LEFT = ("left", "left side (−X down)", 0, -1)
    RIGHT = ("right", "right side (+X down)", 0, +1)
    FRONT = ("front", "front edge (+Y down)", 1, +1)
    BACK = ("back", "back edge (−Y down)", 1, -1)

    def __init__(self, short: str, label: str, axis: int, sign: int):
        self.short, self.label, self.axis, self.sign = short, label, axis, sign

    @property
    def down(self) -> np.ndarray:
        v = np.zeros(3)
        v[self.axis] = self.sign
        return v


class Nudge(Enum):
    """What the guidance asks for now."""

    TURN = "turn"  # a side is down and not done: turn it a full circle
    LAY = "lay"  # lay the board on the next side not done
    DONE = "done"  # every side done
    FIELD_ONLY = "field_only"  # no accelerometer: the field-relative hint applies


@dataclass(frozen=True)
class Advice:
    nudge: Nudge
    side: Side | None  # the side to turn on or to lay it on
    still: bool  # the board has not moved for STILL_S
    text: str  # one sentence for the user ("" for FIELD_ONLY when moving)
    checklist: str  # the six sides, ticked ("" without an accelerometer)


def side_down(accel_g) -> Side | None:
    """The side the board lies on, from one accelerometer reading (any unit); None between
    sides or for a reading of no direction."""
    a = np.asarray(accel_g, dtype=np.float64)
    norm = float(np.linalg.norm(a))
    if not np.isfinite(norm) or norm == 0:
        return None
    down = -a / norm
    k = int(np.argmax(np.abs(down)))
    if abs(down[k]) < SIDE_COS:
        return None
    return next(s for s in Side if s.axis == k and s.sign == np.sign(down[k]))


def heading_bin(field_ut, down) -> int | None:
    """The 30° heading of the field's horizontal part about ``down`` (None when the field is
    too near the vertical to tell)."""
    u = np.asarray(field_ut, dtype=np.float64)
    d = np.asarray(down, dtype=np.float64)
    h = u - (u @ d) * d
    if np.linalg.norm(h) < MIN_HORIZONTAL * np.linalg.norm(u):
        return None
    e1 = np.roll(d, 1)  # any axis other than down, made perpendicular
    e1 = e1 - (e1 @ d) * d
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    angle = np.arctan2(h @ e2, h @ e1) % (2 * np.pi)
    return int(angle / (2 * np.pi) * HEADING_BINS) % HEADING_BINS


@dataclass
class Guide:
    """The guidance's memory: headings seen per side, when the board last moved, whether an
    accelerometer was ever read. ``chip``: the part whose IMU axes name the sides (None: the
    samples' accelerometer is already in the printed axes, as a MotionCal board sends it)."""

    chip: Chip | None = None
    seen: dict = field(default_factory=lambda: {s: set() for s in Side})
    has_accel: bool = False
    side: Side | None = None
    t_s: float | None = None
    _t_moved: float | None = None
    _u_ref: np.ndarray | None = None

    def update(self, t_s: float, field_ut, accel_g=None) -> None:
        """One look at the board: the field (about the calibration's centre) and, when the
        board sends one, the accelerometer."""
        u = np.asarray(field_ut, dtype=np.float64)
        if not np.all(np.isfinite(u)) or not np.any(u):
            return
        u = u / np.linalg.norm(u)
        self.t_s = t_s
        if self._u_ref is None or np.degrees(np.arccos(np.clip(u @ self._u_ref, -1, 1))) > MOVE_DEG:
            self._u_ref, self._t_moved = u, t_s
        if accel_g is None:
            return
        self.has_accel = True
        printed = accel_g if self.chip is None else self.chip.mag_to_accel(accel_g)
        self.side = side_down(printed)
        if self.side is not None:
            down = self.side.down if self.chip is None else self.chip.accel_to_mag(self.side.down)
            b = heading_bin(u, down)
            if b is not None:
                self.seen[self.side].add(b)

    def still(self) -> bool:
        return self._t_moved is not None and self.t_s - self._t_moved >= STILL_S

    def done(self, side: Side) -> bool:
        return len(self.seen[side]) >= DONE_BINS

    def advice(self) -> Advice:
        still = self.still()
        if not self.has_accel:
            return Advice(Nudge.FIELD_ONLY, None, still, "you are not moving: turn the board" if still else "", "")
        checklist = "sides: " + "  ".join(("✓ " if self.done(s) else "· ") + s.short for s in Side)
        nudge, side, text = self._next()
        if still and nudge is not Nudge.DONE:
            text = "you are not moving: " + text
        return Advice(nudge, side, still, text, checklist)

    def _next(self) -> tuple[Nudge, Side | None, str]:
        if self.side is not None and not self.done(self.side):
            swept = 360 * len(self.seen[self.side]) // HEADING_BINS
            return Nudge.TURN, self.side, (f"turn it a full circle as it lies {_on(self.side)} "
                                           f"({swept}° of 360° so far)")
        todo = [s for s in Side if not self.done(s)]
        if not todo:
            return Nudge.DONE, None, "every side done: keep turning slowly while the fit settles"
        return Nudge.LAY, todo[0], f"lay it {_on(todo[0])}, then turn it a full circle"


def _on(side: Side) -> str:
    return side.label if side in (Side.BOTTOM, Side.TOP) else f"on its {side.label}"
