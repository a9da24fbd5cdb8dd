"""The session state machine and its gates (pure: no device)."""

import numpy as np
import pytest

from magcal.core.events import Event
from magcal.core.sample import Sample
from magcal.logic import failures
from magcal.logic.failures import Failure, Reason
from magcal.logic.gates import Gates
from magcal.logic.session import Session, Status
from magcal.sim.physics import Motion, Scenario, demo_scenario


def samples_from(scenario, n, rate=50.0):
    run = scenario.simulate(n, rate)
    s = run.series
    return [Sample(seq=i, t_s=float(s.t_s[i]), field_ut=tuple(s.field_ut[i]), raw=tuple(int(v) for v in run.raw[i]),
                   st2=int(run.st2[i])) for i in range(n)]


def test_full_sphere_motion_becomes_ready_and_solves_near_truth():
    sc = demo_scenario(5)
    s = Session(Gates())
    for smp in samples_from(sc, 4000):
        s.add(smp)
        if s.ready():
            break
    assert s.ready(), [g.message for g in s.failing_gates()]
    result = s.solve()
    assert result and s.status is Status.SOLVING
    assert np.allclose(result.calibration.offset_ut, sc.physics.hard_iron_ut, atol=0.3)


def test_flat_turns_never_pass_coverage():
    sc = Scenario(motion=Motion("yaw"), seed=2)
    s = Session(Gates())
    s.add_many(samples_from(sc, 4000))
    names = [g.name for g in s.failing_gates()]
    assert "min_coverage" in names and not s.ready()


def test_flagged_samples_and_events_are_counted_not_used():
    s = Session()
    s.add(Sample(seq=1, t_s=0.0, field_ut=(1.0, 2.0, 3.0), raw=(4095, 2, 3), st2=0))
    s.add(Sample(seq=2, t_s=0.0, field_ut=(1.0, 2.0, 3.0), raw=(5, 2, 3), st2=0x08))
    s.add(Event("gap", seq=9, count=6))
    assert s.accumulator.n == 0
    assert s.counters["rejected_flagged"] == 2 and s.counters["lost_samples"] == 6


def test_transitions_outside_the_diagram_are_refused():
    s = Session()
    with pytest.raises(RuntimeError, match="collecting to writing"):
        s.begin_write()
    with pytest.raises(TypeError, match="Failure"):
        s.fail("timeout", "gave up")  # a code as text is refused: the failure is a typed value
    s.fail(failures.TIMEOUT, "gave up")
    assert s.status is Status.FAILED and s.failure.reason is Reason.TIMEOUT
    with pytest.raises(RuntimeError):
        s.solve()


def test_final_gates_can_refuse_a_fit():
    sc = demo_scenario(5)
    s = Session(Gates(field_range_ut=(60.0, 100.0), min_samples=50, min_coverage=0.3, max_offset_sigma_ut=5))
    s.add_many(samples_from(sc, 3000))
    s.solve()
    assert s.status is Status.FAILED and s.failure == Failure(Reason.GATE, "field_range")
    assert "field radius" in s.failure_message
