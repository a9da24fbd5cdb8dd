"""``magcal fit`` on several recordings of one board: each fitted, each compared with the one
before — did the hard iron move between sessions?"""

import json

import pytest

from magcal.cli import main


def test_several_sessions_are_fitted_and_a_moved_hard_iron_is_named(tmp_path, capsys):
    paths = []
    for seed, offset in ((1, "20,-30,10"), (2, "20,-30,10"), (3, "21.5,-30,10")):
        p = tmp_path / f"s{seed}.csv"
        assert main(["simulate", "-o", str(p), "--seed", str(seed), "--offset", offset]) == 0
        paths.append(str(p))
    bad = tmp_path / "bad.csv"
    bad.write_text("x\n")
    capsys.readouterr()
    code = main(["fit", paths[0], paths[1], str(bad), paths[2], "--json"])
    out, err = capsys.readouterr()
    d = json.loads(out)
    assert code == 6 and "bad.csv" in err  # the unreadable file is named, the others are fitted
    assert [f["file"] for f in d["fits"]] == [paths[0], paths[1], str(bad), paths[2]]
    assert "error" in d["fits"][2] and d["fits"][3]["calibration"]["offset_ut"][0] == pytest.approx(21.5, abs=0.1)
    same, moved = d["comparisons"]
    assert (same["from"], same["to"], moved["from"], moved["to"]) == (paths[0], paths[1], paths[1], paths[2])
    assert not same["offset_moved"] and same["p_value"] > 0.01
    assert moved["offset_moved"] and moved["offset_change_ut"][0] == pytest.approx(1.5, abs=0.1)
    assert main(["fit", paths[1], paths[2]]) == 0
    assert "the hard iron changed between these sessions" in capsys.readouterr().out
