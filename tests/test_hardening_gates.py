"""Every gate judged on every write path: a result carries its evidence, ``write`` recomputes
what a result lacks from the recording it names, and refuses (exit 3, naming the gate) what it
can judge neither way — unless ``--force``."""

import json

import pytest

from magcal.cli import main

GATES = ("n_used", "coverage", "condition", "rms_ut", "offset_sigma_ut")


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    for name, motion, seconds in (("sphere", "sphere", 120), ("tilt", "tilt", 30)):
        assert main(["simulate", "-o", str(d / f"{name}.csv"), "--motion", motion, "--seconds", str(seconds),
                     "--seed", "3", "-q"]) == 0
    return d


def _fit(capsys, path) -> dict:
    code, out, _ = run_cli(capsys, "fit", str(path), "--json")
    assert code == 0
    return json.loads(out)


def _write(capsys, tmp_path, doc, *extra):
    src = tmp_path / "result.json"
    src.write_text(json.dumps(doc))
    ee = tmp_path / "ee.bin"
    code, out, err = run_cli(capsys, "write", str(src), "--port", f"sim://?pace=0&eeprom={ee}", "--json", *extra)
    return code, json.loads(out), ee


def test_a_fit_result_carries_every_gates_evidence(capsys, recordings):
    ev = _fit(capsys, recordings / "sphere.csv")["fits"][0]["evidence"]
    assert set(GATES) <= set(ev) and all(ev[k] is not None for k in GATES)
    assert 0.55 < ev["coverage"] <= 1 and ev["n_used"] > 1000 and len(ev["offset_sigma_ut"]) == 3


def test_a_thin_recording_fitted_offline_is_refused_on_coverage(capsys, recordings, tmp_path):
    """The tilt motion covers too few directions: ``calibrate`` would refuse it, and so does
    ``fit --json | write`` — nothing is sent."""
    code, r, ee = _write(capsys, tmp_path, _fit(capsys, recordings / "tilt.csv"))
    assert code == 3 and r["failed_gate"] == "min_coverage" and not r["written"]
    assert not ee.exists()


def test_evidence_cut_from_a_result_is_recomputed_from_its_recording(capsys, recordings, tmp_path):
    doc = _fit(capsys, recordings / "sphere.csv")
    for k in ("evidence", "rms_ut", "n_used", "uncertainty", "condition", "coverage"):
        doc["fits"][0].pop(k)
    code, r, _ = _write(capsys, tmp_path, doc)
    assert code == 0 and r["verified"] and r["gates"]["not_judged"] == []
    assert any("recomputed" in n for n in r["notes"])


def test_evidence_that_cannot_be_had_refuses_unless_forced(capsys, recordings, tmp_path):
    doc = _fit(capsys, recordings / "sphere.csv")
    fit = doc["fits"][0]
    for k in ("evidence", "rms_ut", "n_used", "uncertainty", "condition", "coverage", "file"):
        fit.pop(k)
    code, r, ee = _write(capsys, tmp_path, doc)
    assert code == 3 and r["failed_gate"] == "min_samples" and not ee.exists()
    assert set(r["gates"]["not_judged"]) == {"min_samples", "min_coverage", "max_condition", "max_rms",
                                             "max_offset_sigma"}
    code, r, _ = _write(capsys, tmp_path, doc, "--force")
    assert code == 0 and r["verified"] and r["gates"]["forced"]


def test_a_recording_that_is_gone_leaves_the_gate_unjudged(capsys, recordings, tmp_path):
    doc = _fit(capsys, recordings / "sphere.csv")
    doc["fits"][0].pop("evidence")
    doc["fits"][0].pop("coverage")
    doc["fits"][0]["file"] = str(tmp_path / "gone.csv")
    code, r, _ = _write(capsys, tmp_path, doc)
    assert code == 3 and "min_coverage" in r["gates"]["not_judged"]


def test_a_result_edited_by_hand_is_judged_on_its_recording(capsys, recordings, tmp_path):
    """Its evidence claimed better than the recording shows, or its calibration moved away from
    the fit: the gates judge what the recording shows for the calibration being written."""
    doc = _fit(capsys, recordings / "tilt.csv")
    doc["fits"][0]["evidence"]["coverage"] = 0.95
    code, r, _ = _write(capsys, tmp_path, doc)
    assert code == 3 and r["failed_gate"] == "min_coverage"
    doc = _fit(capsys, recordings / "sphere.csv")
    doc["fits"][0]["calibration"]["offset_ut"][0] += 8.0
    code, r, ee = _write(capsys, tmp_path, doc)
    assert code == 3 and r["failed_gate"] == "max_rms" and not ee.exists()
