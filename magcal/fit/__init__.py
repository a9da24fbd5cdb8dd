"""Fits: each a constructor that returns a model or a falsy FitFailure, never a half-built object.

``fit_calibration(samples, model="sphere"|"ellipsoid"|"auto", outliers=True)`` is the entry point the
session, the CLI and the diagnosis use; the pieces (accumulator, ML sphere, ellipsoid, Grubbs,
uncertainty) are importable on their own.
"""

from .accumulator import SphereAccumulator, SphereFit
from .ellipsoid import algebraic_quadric, fit_ellipsoid, quadric_to_correction
from .failure import FitFailure
from .outliers import grubbs, grubbs_critical
from .pipeline import MODELS, fit_calibration, fit_models
from .result import FitResult
from .sphere import fit_sphere

__all__ = [
    "SphereAccumulator", "SphereFit", "FitFailure", "FitResult", "fit_calibration", "fit_models", "MODELS",
    "fit_sphere", "fit_ellipsoid", "algebraic_quadric", "quadric_to_correction",
    "grubbs", "grubbs_critical",
]
