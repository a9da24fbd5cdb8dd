"""Model discovery: find the physics a calibration left out, model it, show the gain.

``diagnose(series) -> Diagnosis``; ``Diagnosis.to_dict()`` is the ``magcal diagnose --json``
object; ``magcal.app.report.write_report(diagnosis, directory)`` draws the evidence.
One module per effect family (softiron, channels, glitches), the model and its fit (model),
the statistics (inference) and the ladder that ties them (ladder).
"""

from .finding import Finding
from .diagnosis import Diagnosis
from .ladder import diagnose

__all__ = ["Diagnosis", "Finding", "diagnose"]
