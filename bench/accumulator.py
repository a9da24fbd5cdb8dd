"""Sphere accumulator throughput: samples per second for add_batch and add, and solve time.

Run: python bench/accumulator.py
"""

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.fit import SphereAccumulator  # noqa: E402


def main() -> None:
    rng = np.random.default_rng(0)
    u = rng.normal(size=(1_000_000, 3))
    m = 50 * u / np.linalg.norm(u, axis=1, keepdims=True) + [300.0, -200.0, 100.0]
    for chunk in (50, 1000, 100_000):
        acc = SphereAccumulator()
        t0 = time.perf_counter()
        for i in range(0, len(m), chunk):
            acc.add_batch(m[i : i + chunk])
        dt = time.perf_counter() - t0
        print(f"add_batch chunk={chunk:>6}: {len(m) / dt:12,.0f} samples/s")
    acc = SphereAccumulator()
    k = 20_000
    t0 = time.perf_counter()
    for row in m[:k]:
        acc.add(row)
    dt = time.perf_counter() - t0
    print(f"add (one at a time):     {k / dt:12,.0f} samples/s")
    t0 = time.perf_counter()
    for _ in range(1000):
        fit = acc.solve()
    print(f"solve: {(time.perf_counter() - t0) * 1e6 / 1000:.1f} µs per call -> offset {np.round(fit.offset_ut, 3)}")


if __name__ == "__main__":
    main()
