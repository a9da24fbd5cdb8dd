"""``magcal fleet``: a fleet's logs (drawn by ``fleet_twin`` from a real flight, with changes
planted at known flights) analysed on the process pool and on a local Dask cluster, a run killed
midway and restarted, the changes found where they were planted, and the history judged as a
user reads it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from logs_extra import need

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FLIGHTS = 5
STEP_AT, CURRENT_AT = 2, 3


def _need_fleet():
    need("pymavlink", "pygeomag")
    need("pyarrow", "distributed", extra="fleet")


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """Three vehicles of five flights: unchanged; the external compass's hard iron steps by
    (6, −4, 3) µT (about 10× its per-flight σ) from flight 2; a current term of 0.5 µT/A
    appears on the external compass from flight 3. Plus one file that is not a readable log."""
    _need_fleet()
    import fleet_twin as ft

    root = tmp_path_factory.mktemp("fleet")
    plants = [ft.Plant(), ft.Plant("hard_iron_step", 0, STEP_AT, (6.0, -4.0, 3.0)),
              ft.Plant("current_appears", 0, CURRENT_AT, (0.3, -0.4, 0.2))]
    vehicles = ft.fleet(3, FLIGHTS, seed=5, plants=plants)
    ft.write_fleet(root / "logs", vehicles)
    with open(root / "logs" / vehicles[0].name / "flight_999.bin", "wb") as fh:
        fh.write(b"\xa3\x95\x80" + bytes(range(256)) * 4)  # a DataFlash head and then nothing a reader can use
    return root, vehicles


def _fleet(*args) -> int:
    from magcal.cli import main

    return main(["fleet", *map(str, args), "-q"])


def _rows(results) -> list[dict]:
    from magcal.app.fleet.store import ResultStore

    return ResultStore(str(results)).rows()


# the tests on the generated fleet share one pool run (seconds: sixteen logs generated and analysed)
FLEET = [pytest.mark.slow, pytest.mark.xdist_group("fleet_logs")]


def _on_fleet(f):
    for m in FLEET:
        f = m(f)
    return f


def _same(a: list[dict], b: list[dict]) -> bool:
    """Row by row, NaN equal to NaN (a term not fitted)."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str)


@pytest.fixture(scope="module")
def pooled(logs):
    root, _ = logs
    assert _fleet(root / "logs", "-o", root / "pool", "--workers", 2) == 0
    return root / "pool"


@_on_fleet
def test_every_log_and_magnetometer_is_a_row_and_a_bad_log_is_a_row_with_its_error(pooled, logs):
    _, vehicles = logs
    rows = _rows(pooled)
    assert len(rows) == 3 * FLIGHTS * 2 + 1
    bad = [r for r in rows if r["status"] != "ok"]
    assert [os.path.basename(r["path"]) for r in bad] == ["flight_999.bin"] and bad[0]["message"]
    good = [r for r in rows if r["status"] == "ok"]
    # the vehicle is the one the log names (the board's id line), not the folder
    assert {r["vehicle"] for r in good} == {" ".join(v.board_line().split()) for v in vehicles}
    assert all(r["vehicle_from"] == "log" and r["mode"] == "vector" for r in good)
    assert {r["external"] for r in good} == {True, False}
    assert all(np.all(np.isfinite(r["sigma_offset_ut"])) and r["flight_time_utc"].startswith("2024-03") for r in good)


@_on_fleet
def test_the_changes_are_found_at_the_planted_flights(pooled, logs):
    _, vehicles = logs
    doc = json.loads((pooled / "fleet.json").read_text())
    by_vehicle = {}
    for c in doc["changes"]:
        by_vehicle.setdefault(c["vehicle"], []).append(c)
    plain, stepped, current = (" ".join(v.board_line().split()) for v in vehicles)
    assert plain not in by_vehicle
    step = [c for c in by_vehicle[stepped] if c["kind"] == "hard_iron_step"]
    assert [(c["compass"], os.path.basename(c["flight"])) for c in step] == [("device 97539", f"flight_{STEP_AT:03d}.bin")]
    assert np.allclose(step[0]["step"], (6.0, -4.0, 3.0), atol=1.0)
    assert step[0]["alone"] is True  # the internal compass did not move: it no longer agrees with this one
    cur = [c for c in by_vehicle[current] if c["kind"] == "current_term_appeared"]
    assert [(c["compass"], os.path.basename(c["flight"])) for c in cur] == [("device 97539", f"flight_{CURRENT_AT:03d}.bin")]
    page = (pooled / "index.html").read_text()
    assert "hard-iron step" in page and "current term appeared" in page and "flight_999.bin" in page


@_on_fleet
def test_a_dask_cluster_gives_the_same_rows_as_the_pool(pooled, logs, tmp_path):
    from distributed import LocalCluster

    root, _ = logs
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        assert _fleet(root / "logs", "-o", tmp_path / "dask", "--scheduler", cluster.scheduler_address) == 0
    assert _same(_rows(tmp_path / "dask"), _rows(pooled))
    assert json.loads((tmp_path / "dask" / "fleet.json").read_text())["changes"] == \
        json.loads((pooled / "fleet.json").read_text())["changes"]


@_on_fleet
def test_a_run_killed_midway_and_restarted_gives_the_same_dataset_with_no_row_twice(pooled, logs, tmp_path):
    root, _ = logs
    out = tmp_path / "resumed"
    cmd = [sys.executable, "-m", "magcal", "fleet", str(root / "logs"), "-o", str(out), "--workers", "1", "-q"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        if len([f for f in os.listdir(out / "rows") if f.endswith(".parquet")] if (out / "rows").exists() else []) >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    kept = [f for f in os.listdir(out / "rows") if f.endswith(".parquet") and not f.startswith(".")]
    assert 3 <= len(kept) < 3 * FLIGHTS + 1, "the run was to be killed midway"
    assert _fleet(root / "logs", "-o", out) == 0
    rows = _rows(out)
    keys = [(r["file_sha256"], r["magcal_version"], r["mag_index"]) for r in rows]
    assert len(keys) == len(set(keys))
    assert _same(rows, _rows(pooled))
    doc = json.loads((out / "fleet.json").read_text())
    assert doc["logs"]["done_before"] == len(kept) and doc["logs"]["analysed"] == 3 * FLIGHTS + 1 - len(kept)


def test_a_manifest_names_the_vehicle_of_a_recording_without_one(tmp_path, capsys):
    _need_fleet()
    import shutil

    src = os.path.join(ROOT, "tests", "data", "lsm9ds1_ckexplorer_every4th.csv")
    shutil.copy(src, tmp_path / "bench.csv")
    (tmp_path / "manifest.csv").write_text("path,vehicle,notes\nbench.csv,rover-7,before the motor swap\n")
    assert _fleet(tmp_path / "manifest.csv", "-o", tmp_path / "out", "--workers", 1, "--json") == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["schema"] == "magcal.fleet/1"
    (row,) = _rows(tmp_path / "out")
    assert (row["vehicle"], row["vehicle_from"], row["notes"], row["status"]) == ("rover-7", "manifest", "before the motor swap", "ok")
    assert doc["vehicles"][0]["compasses"][0]["flights"][0]["offset_ut"] == row["offset_ut"]


def test_no_logs_in_the_sources_is_an_input_error(tmp_path):
    _need_fleet()
    (tmp_path / "notes.md").write_text("nothing here\n")
    assert _fleet(tmp_path, "-o", tmp_path / "out") == 6


# -- the history judged (pure: rows in, changes out) --------------------------------------------
def _history(offsets, sigma=0.2, vehicle="V", compass="c0", current=None):
    rows = []
    for j, off in enumerate(offsets):
        rows.append({"vehicle": vehicle, "compass": compass, "path": f"f{j:03d}", "flight_year": 2024.0 + j / 365,
                     "offset_ut": list(off), "sigma_offset_ut": [sigma] * 3,
                     "current_a_ut_per_unit": list(current[j]) if current is not None else [float("nan")] * 3,
                     "sigma_current_a_ut_per_unit": [0.01] * 3})
    return rows


def _noisy(n, seed, sigma=0.2, step_at=None, step=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    x = rng.normal(0.0, sigma, (n, 3)) + (10.0, -5.0, 30.0)
    if step_at is not None:
        x[step_at:] += step
    return x


def test_a_hard_iron_step_is_named_at_its_flight_and_an_unchanged_compass_is_not():
    from magcal.logic.fleet import ChangeKind, detect

    rows = _history(_noisy(12, 1, step_at=7, step=(1.2, 0.0, 0.0)))
    (c,) = detect(rows).changes
    assert (c.kind, c.flight, c.previous_flight) == (ChangeKind.HARD_IRON_STEP, "f007", "f006")
    assert abs(c.after[0] - c.before[0] - 1.2) < 0.3
    assert not any(detect(_history(_noisy(12, seed))).changes for seed in range(2, 12))


def test_flights_scattering_beyond_their_sigma_widen_it_instead_of_making_a_change():
    """σ claimed 4× too small: the scatter between flights says so, and no change is called."""
    from magcal.logic.fleet import detect

    for seed in range(5):
        rows = _history(_noisy(15, seed, sigma=0.8), sigma=0.2)
        assert not detect(rows).changes


def test_a_change_on_one_compass_alone_and_on_every_compass_are_told_apart():
    from magcal.logic.fleet import detect

    moved = _history(_noisy(10, 3, step_at=5, step=(0.0, 2.0, 0.0)), compass="external")
    held = _history(_noisy(10, 4), compass="internal")
    (c,) = detect(moved + held).changes
    assert c.alone is True and c.siblings[0].compass == "internal" and not c.siblings[0].moved
    both = moved + _history(_noisy(10, 5, step_at=5, step=(0.0, 1.5, 0.5)), compass="internal")
    changes = detect(both).changes
    assert len(changes) == 2 and all(c.alone is False for c in changes)


def test_a_current_term_that_appears_is_told_from_one_that_grows():
    from magcal.logic.fleet import ChangeKind, detect

    off = _noisy(8, 6)
    appears = np.zeros((8, 3))
    appears[4:] = (0.2, -0.1, 0.0)
    (c,) = detect(_history(off, current=appears + np.random.default_rng(1).normal(0, 0.01, (8, 3)))).changes
    assert (c.kind, c.flight) == (ChangeKind.CURRENT_TERM_APPEARED, "f004")
    grows = appears + (0.3, 0.0, 0.0)
    (c,) = detect(_history(off, current=grows + np.random.default_rng(2).normal(0, 0.01, (8, 3)))).changes
    assert c.kind is ChangeKind.CURRENT_TERM_CHANGED


def _dies_on_the_second(task):
    """A worker that dies on one file (as a crash in a parser's compiled code would)."""
    from magcal.app.fleet.analyse import analyse

    if task["path"].endswith("second.csv"):
        os._exit(3)
    return analyse(task)


def test_a_log_that_kills_its_worker_process_is_a_row_and_the_run_goes_on(tmp_path, monkeypatch):
    _need_fleet()
    import shutil

    from magcal.app.fleet import runner

    data = os.path.join(ROOT, "tests", "data")
    shutil.copy(os.path.join(data, "lsm9ds1_ckexplorer_every4th.csv"), tmp_path / "first.csv")
    shutil.copy(os.path.join(data, "qmc5883l_tomisuarez_every5th_counts.csv"), tmp_path / "second.csv")
    monkeypatch.setattr(runner, "analyse", _dies_on_the_second)
    assert _fleet(tmp_path / "first.csv", tmp_path / "second.csv", "-o", tmp_path / "out", "--workers", 2) == 0
    rows = {os.path.basename(r["path"]): r for r in _rows(tmp_path / "out")}
    assert rows["first.csv"]["status"] == "ok"
    assert (rows["second.csv"]["status"], rows["second.csv"]["failure"]) == ("unreadable", "WorkerDied")


def test_a_manifest_row_whose_file_is_missing_is_a_row_saying_so(tmp_path):
    _need_fleet()
    (tmp_path / "manifest.csv").write_text("path,vehicle\ngone.bin,rover-7\n")
    assert _fleet(tmp_path / "manifest.csv", "-o", tmp_path / "out", "--workers", 1) == 0
    (row,) = _rows(tmp_path / "out")
    assert (row["vehicle"], row["status"]) == ("rover-7", "unreadable") and "gone.bin" in row["message"]


def test_a_compass_seen_on_one_flight_is_stated_in_words_not_drawn_as_an_empty_history():
    """A fleet of first flights: each compass's numbers in a sentence (its chart was a lone
    point at the left edge of an empty box), and counts in the singular where there is one."""
    from magcal.app.fleet.page import _compass_block

    flight = {"offset_ut": [1.5, -2.0, 3.25], "sigma_offset_ut": [0.2, 0.2, 0.5],
              "current_a_ut_per_unit": [0.1, 0.0, -0.2], "sigma_current_a_ut_per_unit": [0.01, 0.01, 0.01]}
    one = _compass_block({"compass": "device 7", "external": True, "flights": [flight], "changes": []})
    assert "1 flight, 0 changes" in one and "<svg" not in one
    assert "(+1.50, -2.00, +3.25) ± (0.20, 0.20, 0.50) µT" in one and "(+0.10, +0.00, -0.20)" in one
    two = _compass_block({"compass": "device 7", "external": True, "flights": [flight, flight], "changes": []})
    assert "2 flights" in two and two.count("<svg") == 2
