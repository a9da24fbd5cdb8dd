"""One result, one calibration: what a user sees in the terminal, in the shared report (HTML) and
in the JSON of the same run carries the same calibration numbers, the one ``write`` and
``export`` take — for a plain recording and for a flight log."""

import html
import json
import re
from pathlib import Path

import numpy as np
import pytest

from cli_inproc import run_magcal
from cli_once import diagnose_both_ways

DATA = Path(__file__).parent / "data"
PLAIN = DATA / "lsm9ds1_ckexplorer_every4th.csv"
LOG = DATA / "ardupilot_log171_excerpt.bin"


def magcal(*args):
    r = run_magcal(*args)
    assert r.returncode == 0, r.stderr
    return r.stdout


def calibration_keys(obj, path="") -> list[str]:
    """Every place a key named "calibration" sits in the JSON, outside ``alternatives``."""
    if isinstance(obj, dict):
        out = [path] if "calibration" in obj else []
        return out + [p for k, v in obj.items() if k != "alternatives" for p in calibration_keys(v, f"{path}/{k}")]
    if isinstance(obj, list):
        return [p for i, v in enumerate(obj) for p in calibration_keys(v, f"{path}/{i}")]
    return []


def text_block(text: str, head: str) -> list[str]:
    """The offset, field and soft-iron rows that follow the line starting with ``head``."""
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(head))
    return lines[i + 1: i + 6]


def plain_page(page: Path) -> str:
    return re.sub(r"\s+", " ", html.unescape(re.sub(r"<[^>]+>", " ", page.read_text())))


def assert_page_shows(shown: str, cal: dict):
    """The page's calibration table: offset with 1σ, field, and the soft iron, as the JSON has them."""
    table = shown[shown.index("offset (hard iron)"): shown.index("residual RMS")]
    assert re.findall(r"(-?[0-9.]+) ± ", table.split("µT")[0]) == [f"{v:.3f}" for v in cal["offset_ut"]]
    assert f"field {cal['field_ut']:.3f} " in table
    for row in cal["soft_iron"]:
        assert " ".join(f"{v:+.5f}" for v in row) in table


def assert_same(a: dict, b: dict):
    for key in ("offset_ut", "field_ut", "soft_iron"):
        np.testing.assert_allclose(a[key], b[key], rtol=1e-9, atol=1e-9)
    assert sorted(a.get("coef_ut_per_unit") or {}) == sorted(b.get("coef_ut_per_unit") or {})
    for k, v in (a.get("coef_ut_per_unit") or {}).items():
        np.testing.assert_allclose(v, b["coef_ut_per_unit"][k], rtol=1e-9, atol=1e-9)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """One diagnosis, printed as JSON and as text (cli_once), its page; and magcal fit's JSON."""
    out = tmp_path_factory.mktemp("plain")
    doc, text = diagnose_both_ways(PLAIN, "--report", out / "page", "--model-out", out / "m.yaml")
    fit = json.loads(magcal("fit", PLAIN, "--json"))["fits"][0]
    return doc, text, out / "page" / "index.html", fit


@pytest.mark.slow
def test_a_plain_recording_shows_one_calibration_in_text_report_and_json(plain):
    doc, text, page, fit = plain
    assert calibration_keys(doc) == [""]
    cal = doc["calibration"]
    # diagnose took fit's calibration, so it has fit's numbers (the field in fit's det W = 1 convention)
    assert doc["final"]["from"] == "fit" and "alternatives" not in doc
    assert_same(cal, fit["calibration"])
    rows = text_block(text, "final ")
    assert rows[0].split()[1:4] == [f"{v:.3f}" for v in cal["offset_ut"]]
    assert rows[1].split()[1] == f"{cal['field_ut']:.3f}"
    shown = plain_page(page)
    assert_page_shows(shown, cal)
    assert f"field {cal['field_ut']:.3f} ± " in shown
    # the sensor model's field is not the calibration's radius, and the text says why
    said = next(ln for ln in text.splitlines() if ln.startswith("model ")) if "model " in text else None
    assert said is None or "radius" in said
    assert "mean calibrated |m|" in doc["model_out"]["why"] and f"{cal['field_ut']:.3f}" in doc["model_out"]["why"]


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """One diagnosis, printed as JSON and as text (cli_once), its page; magcal fit's JSON and text."""
    out = tmp_path_factory.mktemp("log")
    doc, text = diagnose_both_ways(LOG, "--mag", "1", "--report", out / "page")
    fit = json.loads(magcal("fit", LOG, "--mag", "1", "--json"))["fits"][0]
    return doc, text, out / "page" / "index.html", fit, magcal("fit", LOG, "--mag", "1"), out


@pytest.mark.slow
@pytest.mark.xdist_group("one_calibration_flight")  # one `flight` setup for both tests under make test -n
def test_a_flight_log_shows_the_flight_log_fits_calibration_everywhere(flight):
    doc, text, page, fit, fit_text, _ = flight
    assert calibration_keys(doc) == [""]
    cal = doc["calibration"]
    assert doc["calibration_from"] == "flight_log" and doc["calibration_model"] == fit["model"]
    assert_same(cal, fit["calibration"])  # magcal fit LOG gives the same calibration
    assert {"motors_on", "current_a"} <= set(cal["coef_ut_per_unit"])
    magnitude = next(a for a in doc["alternatives"] if a["name"] == "magnitude")
    assert "|m|" in magnitude["why"] and magnitude["calibration"]["offset_ut"] != cal["offset_ut"]
    # the terminal: the calibration block carries these numbers, the |m| one is named an alternative
    rows = text_block(text, "calibration ")
    assert rows[0].split()[1:4] == [f"{v:.3f}" for v in cal["offset_ut"]]
    assert rows[1].split()[1] == f"{cal['field_ut']:.3f}"
    for name, k in cal["coef_ut_per_unit"].items():
        assert f"coef_{name:<7}" + " ".join(f"{v:9.4f}" for v in k) in text
    assert "(|m| alone: an alternative" in text and "alternative magnitude:" in text
    # the shared report: the same calibration, the vector fit's terms, expected against measured per axis
    shown = plain_page(page)
    assert_page_shows(shown, cal)
    for name, k in cal["coef_ut_per_unit"].items():
        assert f"{name} term" in shown and f"{k[0]:.4f}" in shown
    current = next(t for t in doc["flight_log"]["terms"] if t["channel"] == "current_a")
    assert current["kept"] and f"{current['p_value']:.2g}" in shown
    assert "expected.png" in page.read_text() and (page.parent / "expected.png").stat().st_size > 0
    assert "carries an offset of its own" not in shown or "the flight-log fit keeps" in shown


@pytest.mark.slow
@pytest.mark.xdist_group("one_calibration_flight")
def test_a_term_whose_coefficient_moved_says_so_and_export_and_write_take_the_one(flight):
    doc, text, _, fit, fit_text, out = flight
    from magcal.cli.write import calibration_from_json, evidence_from_json

    step = doc["calibration"]["coef_ut_per_unit"]["motors_on"]
    said = "(" + ", ".join(f"{v:+.3f}" for v in step) + ")"
    judged = next(t for t in fit["terms"] if t["channel"] == "motors_on")
    assert np.linalg.norm(np.subtract(judged["coef_ut_per_unit"], step)) > 1.0  # the step moved with the current
    assert f"in the calibration, fitted together with current_a: {said}" in fit_text
    assert f"in the calibration, fitted together with current_a: {said}" in text
    (out / "d.json").write_text(json.dumps(doc))
    param = magcal("export", out / "d.json", "--ardupilot", "-o", out / "d.param")
    assert "d.param" in param and ", ".join(f"{v:+.2f}" for v in step) in (out / "d.param").read_text()
    for obj in (doc, {"fits": [fit]}):
        written, _ = calibration_from_json(obj)
        np.testing.assert_allclose(written.offset_ut, doc["calibration"]["offset_ut"])
        assert evidence_from_json(obj, written).rms_ut == pytest.approx(fit["rms_ut"])


@pytest.mark.slow
def test_a_px4_log_diagnosis_and_fit_export_the_same_parameters(tmp_path):
    ulog = DATA / "px4_esc_status_excerpt.ulg"
    diag, fit = tmp_path / "d.json", tmp_path / "f.json"
    diag.write_text(magcal("diagnose", ulog, "--json"))
    fit.write_text(magcal("fit", ulog, "--json"))
    doc = json.loads(diag.read_text())
    assert calibration_keys(doc) == [""] and doc["calibration_from"] == "flight_log"
    assert_same(doc["calibration"], json.loads(fit.read_text())["fits"][0]["calibration"])
    for src in (diag, fit):
        magcal("export", src, "--px4", "-o", src.with_suffix(".params"))
    assert diag.with_suffix(".params").read_text() == fit.with_suffix(".params").read_text()


def test_diagnosis_gives_fits_calibration_in_fits_numbers():
    """A calibration diagnosis takes from fit is written with fit's field and soft iron (det W = 1),
    not rescaled by the model's own trace-3 convention: 2 % soft iron already moved the field."""
    from magcal.diagnose.diagnosis import calibration_dict
    from magcal.diagnose.model import from_calibration
    from magcal.fit import fit_calibration
    from magcal.recordings.table import load_table

    series = load_table(str(PLAIN))
    result = fit_calibration(series, model="ellipsoid")
    theirs = result.to_dict()["calibration"]
    model = from_calibration(result.calibration, result.model, result.n_used, result.rms_ut)
    assert abs(model.field_ut - theirs["field_ut"]) > 1e-3  # the model's own scale differs …
    assert_same(calibration_dict(model), theirs)  # … and the JSON's calibration is fit's


def test_a_log_result_keeps_the_magnitude_calibration_only_as_an_alternative():
    from magcal.cli.diagnose import log_calibration_lines, take_log_calibration

    vector = {"offset_ut": [1.0, 2.0, 3.0], "field_ut": 50.0, "soft_iron": np.eye(3).tolist(),
              "coef_ut_per_unit": {"current_a": [0.1, 0.2, 0.3]}, "reference": {"current_a": 0.0}}
    magnitude = {"offset_ut": [4.0, 5.0, 6.0], "field_ut": 49.0, "soft_iron": np.eye(3).tolist()}
    d = {"final": {"model": "sphere", "from": "fit"}, "calibration": magnitude,
         "flight_log": {"model": "vector+current_a", "mode": "vector", "calibration": vector,
                        "uncertainty": {"offset_ut": [0.1, 0.1, 0.1]}}}
    take_log_calibration(d)
    assert calibration_keys(d) == [""] and d["calibration"] is vector
    assert [a["calibration"] for a in d["alternatives"]] == [magnitude]
    text = "\n".join(log_calibration_lines(d))
    assert "offset_ut       1.000     2.000     3.000   ± 0.100 0.100 0.100" in text
    assert "alternative magnitude: offset (4.000, 5.000, 6.000) µT, field 49.000 µT" in text


@pytest.mark.slow
def test_a_log_whose_magnitude_was_not_diagnosed_still_gets_its_page(tmp_path):
    """A mostly level flight: |m| alone cannot be diagnosed, but the page of the flight-log fit
    — its calibration, terms and expected against measured field — is still written."""
    from magcal.app.flightlog import diagnose_flight_log, vector_traces
    from magcal.app.report import write_log_report
    from magcal.cli.diagnose import take_log_calibration
    from magcal.recordings.logs import load_log

    lm = load_log(str(LOG), 2)
    d = {"n_samples": len(lm.series), "magnitude_failure": "a cloud, not a sphere", "flight_log": diagnose_flight_log(lm)}
    take_log_calibration(d)
    assert calibration_keys(d) == [""] and "alternatives" not in d
    page = write_log_report(d, vector_traces(lm, d["calibration"]), tmp_path / "page", title="log")
    shown = plain_page(page)
    assert_page_shows(shown, d["calibration"])
    assert "a cloud, not a sphere" in shown and (tmp_path / "page" / "expected.png").exists()
    assert "current_interference (against the expected field)" in shown
