"""Limits as values: each kind keeps the JSON shape ``magcal.diagnose/1`` has always had (its
keys in their order), and a limit given as a dict in any other shape is refused by name."""

import json

import numpy as np
import pytest

from magcal.diagnose import statements
from magcal.diagnose.claims import Refused
from magcal.diagnose.hygiene import LeftOut
from magcal.diagnose.heldout import HeldOut, never_worse
from magcal.diagnose.limits import Limit
from magcal.diagnose.model import ModelFit, Spec


def _keys(limit: Limit) -> list[str]:
    return list(json.loads(json.dumps(limit.to_dict())))


def test_a_left_out_channel_states_why_in_the_json_and_to_the_report():
    (limit,) = statements.left_out((LeftOut("mag_x_counts", "a magnetometer reading", 0.97),))
    assert _keys(limit) == ["effect", "suspected", "channel", "left_out", "reason", "orientation_share", "summary"]
    d = limit.to_dict()
    assert d["effect"] == "covariate:mag_x_counts" and d["left_out"] is True and d["suspected"] is False
    assert limit.left_out and limit.left_out_because == d["reason"] == "a magnetometer reading"
    assert d["orientation_share"] == 0.97


def test_a_refused_claim_and_a_calibration_fit_did_better_keep_their_shapes():
    refused = Refused("time_drift", "each half of the recording shows far less of it than the whole").limit()
    assert _keys(refused) == ["effect", "suspected", "check", "summary"]
    assert refused.suspected and refused.to_dict()["check"] == "claims" and not refused.left_out
    sphere = ModelFit(Spec(), np.array([1.0, 2.0, 3.0, 50.0]), {}, 0.4, 100, 5)
    worse = never_worse(sphere, sphere, HeldOut((0.3, 0.52, 0.50), ()))
    assert _keys(worse) == ["effect", "suspected", "heldout_rms_ut_diagnosis", "heldout_rms_ut_fit", "summary"]
    assert worse.effect == "calibration" and "0.500 µT against 0.520 µT" in worse.summary
    assert never_worse(sphere, sphere, HeldOut((0.3, 0.50, 0.52), ())) is None


def test_a_located_remainder_keeps_its_summary_and_where_first():
    d = {"effect": "unexplained_structure", "suspected": True, "summary": "Structure located …",
         "where": {"time_s": [3.0]}, "params": {"step_ut": [1.0, 0.0, 0.0]}, "resembles": "hard_iron_step"}
    limit = Limit.from_dict(d)
    assert limit.where == {"time_s": [3.0]} and limit.details["resembles"] == "hard_iron_step"
    assert json.dumps(limit.to_dict()) == json.dumps(d)


def test_a_limit_in_another_shape_is_refused_by_name():
    with pytest.raises(ValueError, match="summary"):
        Limit.from_dict({"effect": "offset_wander", "suspected": True})
    with pytest.raises(ValueError, match="order"):
        Limit.from_dict({"effect": "offset_wander", "summary": "…", "suspected": True})
