"""The one failure vocabulary (magcal.logic.failures) and the exit status it decides, and the
fit's failure value (magcal.fit.failure.FitFailure) when it is used as if it were a model."""

import json

import pytest

from magcal.cli.exits import Exit, exit_for
from magcal.fit import fit_calibration
from magcal.logic import failures
from magcal.logic.failures import Failure, Reason


def test_every_reason_has_an_exit_status_the_data_3_the_write_4():
    codes = {r: exit_for(Failure(r, "field_range" if r is Reason.GATE else None)) for r in Reason}
    assert {r for r, c in codes.items() if c is Exit.WRITE} == {
        Reason.WRITE_FAILED, Reason.VERIFY_MISMATCH, Reason.VERIFY_FAILED}
    assert all(c is Exit.GATE for r, c in codes.items() if c is not Exit.WRITE)


def test_a_gate_failure_names_its_gate_and_reads_as_two_json_fields():
    f = Failure.of_gate("min_coverage")
    assert json.loads(json.dumps(failures.fields(f))) == {"failure": "gate", "failed_gate": "min_coverage"}
    assert failures.fields(None) == {"failure": None, "failed_gate": None}
    assert failures.fields(failures.VERIFY_FAILED)["failure"] == "verify_failed"
    with pytest.raises(ValueError, match="names its gate"):
        Failure(Reason.GATE)
    with pytest.raises(ValueError, match="names its gate"):
        Failure(Reason.TIMEOUT, "min_coverage")
    with pytest.raises(TypeError, match="Reason"):
        Failure("timeout")


def test_a_failed_fit_used_as_a_model_says_the_fit_failed_and_why():
    fit = fit_calibration([[1.0, 2.0, 3.0]] * 3)
    assert not fit and fit.reason == "too_few_samples"
    with pytest.raises(AttributeError, match=r"the fit failed \(too_few_samples: .*only reason and message"):
        fit.calibration  # noqa: B018
    assert not hasattr(fit, "offset_ut") and fit.message
