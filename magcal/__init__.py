"""magcal — magnetometer calibration for the InvenSense MPU-9150 (AK8975).

Rings, from the inside out (see README "Architecture"):
values (sample, calibration) → pure logic (protocol, fit, coverage, diagnose, session)
→ I/O (devices, capture) → effects (daemon, cli).
"""

__version__ = "0.1.0"
