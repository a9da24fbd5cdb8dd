"""Fits: each a constructor that returns a model or a falsy FitFailure, never a half-built object."""

from .accumulator import SphereAccumulator, SphereFit
from .failure import FitFailure

__all__ = ["SphereAccumulator", "SphereFit", "FitFailure"]
