"""Standalone mode on the real firmware: the board collects samples and solves the sphere fit
itself in float32. Centred sums (first sample subtracted) keep the precision the naive sums of
the seed sketch lose when the hard-iron offset is realistic.

Both fits run under the emulator while the board streams, so the host sees exactly the samples
each fit used (those between the command's acknowledgement and the ``F`` reply) and compares the
board's answer with a float64 least-squares fit of the same samples."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from firmware_support import require_firmware

from magcal.core.sample import ST2_DERR, ST2_HOFL
from magcal.devices import open_device
from magcal.sim.physics import Motion, demo_scenario
from magcal.wire.protocol import FitReply

N = 800
OFFSET_UT = (260.0, -215.0, 180.0)  # ≈ 720, −600, 520 counts of hard iron


@pytest.fixture(autouse=True)
def _firmware():
    require_firmware()


def _lsq_sphere(p: np.ndarray) -> tuple[np.ndarray, float]:
    a = np.c_[p, np.ones(len(p))]
    q = np.linalg.lstsq(a, (p**2).sum(axis=1), rcond=None)[0]
    c = q[:3] / 2
    return c, float(np.sqrt(q[3] + c @ c))


def _run_fit(dev, naive: bool):
    fit: FitReply = dev.standalone_fit(N, naive=naive, timeout_s=60)
    samples = [s for s in dev.read(0.2) if hasattr(s, "raw") and s.raw is not None]
    used = [s for s in samples if s.seq < fit.seq and not s.st2 & (ST2_DERR | ST2_HOFL)][-N:]
    assert len(used) == N == fit.n
    p = np.array([s.field_ut for s in used])
    ref_c, ref_r = _lsq_sphere(p)
    board_c = np.array(fit.offset_nt) / 1000.0
    board_r = fit.radius_nt / 1000.0
    return board_c, board_r, ref_c, ref_r, fit


@pytest.mark.slow
def test_centred_float32_sums_keep_precision_that_naive_sums_lose(tmp_path):
    sc = demo_scenario(5).with_physics(hard_iron_ut=OFFSET_UT,
                                       distortion=((1, 0, 0), (0, 1, 0), (0, 0, 1)))
    sc = replace(sc, motion=Motion("sphere", period_s=4.0))  # full coverage within one fit
    dev = open_device(f"emu://?eeprom={tmp_path / 'ee.bin'}", scenario=sc)
    with dev:
        dev.open()
        dev.start(100)
        dev.read(0.2)
        c_c, c_r, ref_c, ref_r, fit_c = _run_fit(dev, naive=False)
        stored = dev.read_record()
        n_c, n_r, nref_c, nref_r, fit_n = _run_fit(dev, naive=True)
        dev.stop()
    err_centred = float(np.linalg.norm(c_c - ref_c))
    err_naive = float(np.linalg.norm(n_c - nref_c))
    truth = np.array(OFFSET_UT)
    msg = (
        f"offset {OFFSET_UT} µT, n={N}: board centred sums → {np.round(c_c, 3)} r={c_r:.3f} "
        f"(float64 fit of the same samples {np.round(ref_c, 3)} r={ref_r:.3f}, error "
        f"{err_centred * 1000:.1f} nT); naive sums → {np.round(n_c, 3)} r={n_r:.3f} (float64 "
        f"{np.round(nref_c, 3)} r={nref_r:.3f}, error {err_naive * 1000:.1f} nT); "
        f"truth {truth}, 50 µT; pivot ratio ×1000 centred {fit_c.cond_milli}, naive {fit_n.cond_milli}"
    )
    print(msg)
    assert err_centred < 0.02, msg           # centred float32 ≈ float64
    assert abs(c_r - ref_r) < 0.02, msg
    assert err_naive > 5 * err_centred, msg  # the naive sums lose precision
    assert np.linalg.norm(c_c - truth) < 0.3, msg
    # the centred system is well conditioned; the naive one is dominated by the offset
    assert fit_c.cond_milli > 10 * max(fit_n.cond_milli, 1), msg
    # the centred fit is stored as the board's record (identity soft iron); the naive one is not
    assert stored.status == "OK"
    assert stored.values[1:5] == (*fit_c.offset_nt, fit_c.radius_nt)
    assert stored.values[5:11] == (1000000, 1000000, 1000000, 0, 0, 0)
