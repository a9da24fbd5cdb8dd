"""The keeper: writes the tracker's calibration only when it is significantly better, never
past a gate, within the EEPROM budget."""

import json

import numpy as np
import pytest

from magcal.core.errors import ConfigError
from magcal.logic.gates import Gates
from magcal.logic.keeper import Budget, DecisionReason, Keeper
from magcal.sim.physics import demo_scenario


def _stream(keeper, m, t, device=None, every=100, log=None):
    """Feed samples, decide every ``every``, 'write' when told; returns the device's calibration."""
    for i in range(len(m)):
        keeper.add(m[i], t[i])
        if (i + 1) % every:
            continue
        d = keeper.decide(device, t[i])
        if log is not None:
            log.append((i, d))
        if d.write:
            device = d.calibration
            keeper.spent(t[i], 1, True)
    return device


@pytest.mark.slow
def test_a_steady_sensor_is_written_once():
    run = demo_scenario(3).simulate(20000, 50.0)
    k, log = Keeper(Gates()), []
    dev = _stream(k, run.series.field_ut, run.series.t_s, log=log)
    writes = [d for _, d in log if d.write]
    assert len(writes) == 1 and writes[0].reason is DecisionReason.FIRST
    assert np.abs(dev.offset_ut - run.truth.offset_ut).max() < 0.3
    later = [d.reason for _, d in log if d.reason is not DecisionReason.GATE and not d.write]
    assert later and set(later) <= {DecisionReason.NOT_SIGNIFICANT, DecisionReason.NO_CALIBRATION}
    assert k.writes == 1 and k.cycles == 1


@pytest.mark.slow
def test_after_a_new_hard_iron_the_restarted_tracker_is_written_once_its_gates_pass():
    sc = demo_scenario(4)
    a = sc.simulate(15000, 50.0).series
    b = sc.with_physics(hard_iron_ut=(30.5, -38.2, 14.8)).simulate(15000, 50.0, t0_s=300.0).series
    k, log = Keeper(Gates()), []
    dev = _stream(k, a.field_ut, a.t_s, log=log)
    first = len([d for _, d in log if d.write])
    k.restart()  # what the daemon does when its drift monitor rings
    dev = _stream(k, b.field_ut, b.t_s, device=dev, log=log)
    later = [(i, d) for i, d in log[len(log) // 2:] if d.write]
    assert first == 1 and later and later[0][1].reason is DecisionReason.BETTER
    assert later[0][0] < 3000  # within a minute of samples at 50 Hz
    assert np.abs(dev.offset_ut - [30.5, -38.2, 14.8]).max() < 0.5
    assert k.writes <= 1 + Budget().burst  # the burst, no more


@pytest.mark.slow
def test_the_budget_holds_writes_back():
    sc = demo_scenario(4)
    a = sc.simulate(15000, 50.0).series
    b = sc.with_physics(hard_iron_ut=(30.5, -38.2, 14.8)).simulate(15000, 50.0, t0_s=300.0).series
    k, log = Keeper(Gates(), Budget(per_day=1.0, burst=1)), []
    dev = _stream(k, a.field_ut, a.t_s)
    k.restart()
    _stream(k, b.field_ut, b.t_s, device=dev, log=log)
    assert k.writes == 1
    assert any(d.reason is DecisionReason.BUDGET and "next write in" in d.message for _, d in log)


def test_never_past_a_gate():
    run = demo_scenario(5).simulate(8000, 50.0)
    k, log = Keeper(Gates(max_rms_ut=0.05)), []
    assert _stream(k, run.series.field_ut, run.series.t_s, log=log) is None
    assert k.writes == 0
    assert log[-1][1].reason is DecisionReason.GATE
    assert any(g["gate"] == "max_rms" for g in log[-1][1].to_dict()["gates"])


def test_state_round_trip_and_bad_settings():
    run = demo_scenario(6).simulate(4000, 50.0)
    k = Keeper(Gates())
    _stream(k, run.series.field_ut, run.series.t_s)
    again = Keeper(Gates())
    again.load_state(json.loads(json.dumps(k.to_state())))
    assert again.status() == k.status()
    with pytest.raises(ValueError, match="malformed"):
        again.load_state({"tracker": k.tracker.to_state()})
    with pytest.raises(ConfigError):
        Keeper(Gates(), Budget(per_day=0))
    assert Budget().years_to_rated_endurance > 10
