"""``magcal track``: replay a recording through the tracker, one record per change."""

import json
import os

import numpy as np

from magcal.cli import main

DATA = os.path.join(os.path.dirname(__file__), "data")
LSM = os.path.join(DATA, "lsm9ds1_ckexplorer_every4th.csv")


def _m():
    return np.loadtxt(LSM, delimiter=",", skiprows=1)


def test_jsonl_one_change_per_line_in_force_after_its_sample(capsys):
    assert main(["track", LSM, "--jsonl", "--rate", "12.5"]) == 0
    recs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(recs) > 20
    for r in recs:
        assert {"sample", "t", "offset_ut", "soft_iron", "field_ut"} <= set(r)
        assert np.shape(r["soft_iron"]) == (3, 3) and len(r["offset_ut"]) == 3
    ks = [r["sample"] for r in recs]
    assert ks == sorted(ks) and ks[-1] <= 2999
    assert abs(recs[-1]["t"] - ks[-1] / 12.5) < 1e-9
    # judged causally (each sample with the calibration in force before it), the second half's
    # |field| spread is a fraction of the uncalibrated one
    m = _m()
    h = []
    for i in range(1500, len(m)):
        r = [x for x in recs if x["sample"] < i][-1]
        h.append(np.linalg.norm(np.asarray(r["soft_iron"]) @ (m[i] - r["offset_ut"])))
    raw = np.linalg.norm(m[1500:] - m.mean(axis=0), axis=1)
    assert np.std(h) / np.mean(h) < 0.25 * np.std(raw) / np.mean(raw)


def test_json_is_versioned_and_ends_with_the_final_calibration(capsys):
    assert main(["track", LSM, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["format"] == "magcal.track" and d["version"] == 1
    assert d["samples"] == 3000 and d["skipped"] == 0
    assert d["final"] == d["changes"][-1]
    assert d["final"]["model"] == "ellipsoid"


def test_the_summary_states_the_json_s_final_calibration_and_its_sigma(capsys):
    assert main(["track", LSM, "--json"]) == 0
    final = json.loads(capsys.readouterr().out)["final"]
    assert main(["track", LSM]) == 0
    out = capsys.readouterr().out
    offset_line = next(x for x in out.splitlines() if x.startswith("offset_ut "))
    stated, sigma = offset_line.split("± (1σ)")
    assert [float(v) for v in stated.split()[1:]] == [round(v, 3) for v in final["offset_ut"]]
    assert [float(v) for v in sigma.split()] == [round(v, 3) for v in final["offset_sigma_ut"]]
    field_line = next(x for x in out.splitlines() if x.startswith("field_ut "))
    assert float(field_line.split()[1]) == round(final["field_ut"], 3)
    assert float(field_line.split()[-1]) == round(final["field_sigma_ut"], 3)


def test_the_summary_lists_each_change_once(capsys):
    # the calibration as reported restates the tracker's last refit at the same sample (σ at
    # least fit's): the JSON keeps both records, the summary one row marked as the reported one
    assert main(["track", LSM, "--json"]) == 0
    changes = json.loads(capsys.readouterr().out)["changes"]
    assert changes[-1]["sample"] == changes[-2]["sample"]
    assert main(["track", LSM]) == 0
    rows = [x.split() for x in capsys.readouterr().out.splitlines() if x.startswith("  sample ")]
    samples = [int(r[1]) for r in rows]
    assert len(samples) == len(set(samples)) and samples[-1] == changes[-1]["sample"]
    assert "as reported" in " ".join(rows[-1])


def test_summary_and_failures(tmp_path, capsys):
    assert main(["track", LSM]) == 0
    out = capsys.readouterr().out
    assert "final       ellipsoid" in out and "soft_iron" in out
    short = tmp_path / "short.csv"
    short.write_text("mx,my,mz\n" + "\n".join(f"{a},{b},{c}" for a, b, c in _m()[:30]) + "\n")
    assert main(["track", str(short)]) == 3
    assert "no calibration came into force" in capsys.readouterr().err
    assert main(["track", LSM, "--rate", "0"]) == 2
    assert "--rate must be positive" in capsys.readouterr().err
    assert main(["track", str(tmp_path / "missing.csv")]) == 6


def test_a_file_in_gauss_is_named_as_such(tmp_path, capsys):
    m = _m()
    gauss = tmp_path / "gauss.csv"
    np.savetxt(gauss, m / 100.0, delimiter=",", header="mx,my,mz", comments="")
    assert main(["track", str(gauss)]) == 3
    err = capsys.readouterr().err
    assert "below the Earth's 15 µT" in err and "--unit gauss" in err
    assert main(["track", str(gauss), "--unit", "gauss"]) == 0


def test_a_flight_log_s_magnetometer_is_chosen_with_mag(capsys):
    # the log holds three; without --mag the error lists them and says to choose with --mag N,
    # which track has to accept
    log = os.path.join(DATA, "ardupilot_log171_excerpt.bin")
    assert main(["track", log]) == 2  # the command line names none of them
    assert "--mag 0: MAG" in capsys.readouterr().err
    main(["track", log, "--mag", "0", "--json"])
    d = json.loads(capsys.readouterr().out)
    assert d["samples"] == 1451 and "--mag 0" in d["input"]
