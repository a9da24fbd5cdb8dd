"""Locate what the catalogue does not know: data faults, steps, lines, lagged channels.

``EFFECTS`` is the one table of located effects; each row comes from the module that owns the
effect (``magcal.diagnose.locate.base.Effect``). ``search(residual)`` runs every row of kind
PHYSICS or REMAINDER on a calibrated recording; data faults are screened before the fit
(``screen_faults``)."""

from __future__ import annotations

from .base import AXES, WHERE_KEYS, Effect, Kind, Located, Residual, runs, stretches

EFFECTS: tuple[Effect, ...] = ()

__all__ = ["AXES", "WHERE_KEYS", "EFFECTS", "Effect", "Kind", "Located", "Residual", "runs", "stretches"]
