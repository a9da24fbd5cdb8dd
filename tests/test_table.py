"""Other people's tables: the column names, units, layouts and separators found in the wild,
and what a user sees when a file cannot be read as asked."""

import json

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.cli import main
from magcal.core.errors import InputError
from magcal.recordings.table import TableFormat, parse_table, plausible_field


def sphere_ut(n=600, offset=(12.0, -30.0, 7.0), field=48.0, seed=3):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.asarray(offset) + field * u + rng.normal(scale=0.2, size=(n, 3))


@pytest.mark.parametrize(
    "header, scale",
    [
        ("mag_x,mag_y,mag_z", 1.0),
        ("MagX,MagY,MagZ", 1.0),
        ("mag_x_ut,mag_y_ut,mag_z_ut", 1.0),
        ("mx_gauss,my_gauss,mz_gauss", 100.0),
        ("Mag_X [mG],Mag_Y [mG],Mag_Z [mG]", 0.1),
        ("magnetometer.x (nT),magnetometer.y (nT),magnetometer.z (nT)", 1e-3),
    ],
)
def test_common_column_names_and_their_units_are_found(header, scale):
    s = parse_table(f"time,{header},acc_x\n0.5,1,2,3,0.1\n1.0,4,5,6,0.2\n", "log.csv")
    assert np.allclose(s.field_ut, scale * np.array([[1, 2, 3], [4, 5, 6]]))
    assert s.t_s.tolist() == [0.5, 1.0]
    assert list(s.channels) == ["acc_x"]


def test_bare_xyz_is_not_taken_for_a_magnetometer():
    with pytest.raises(InputError, match="--columns"):
        parse_table("x,y,z\n1,2,3\n", "acc.csv")


def test_two_magnetometer_triples_must_be_chosen_between():
    text = "mag_x,mag_y,mag_z,compass_x,compass_y,compass_z\n1,2,3,4,5,6\n"
    with pytest.raises(InputError, match="more than one magnetometer triple"):
        parse_table(text, "two.csv")
    s = parse_table(text, "two.csv", TableFormat(columns=("compass_x", "compass_y", "compass_z")))
    assert s.field_ut.tolist() == [[4, 5, 6]]
    assert s.channels == {}  # the other magnetometer measures the same field: not a covariate


def test_a_headerless_logger_dump_read_by_position():
    # the layout of a board printing gyro, accel, mag (gauss), time (ms), … with a nan column
    rows = ["0.01, 0.02, 0.03, 0.1, 0.2, 9.8, 0.25, -0.125, 0.5, 1000.0, nan",
            "0.01, 0.02, 0.03, 0.1, 0.2, 9.8, 0.26, -0.125, 0.5, 1020.0, 0.3"]
    text = "\n".join(rows) + "\n"
    with pytest.raises(InputError, match=r"first line is numbers, not a header.*--columns"):
        parse_table(text, "putty.log")
    fmt = TableFormat(columns=("7", "8", "9"), unit="gauss", time="10", time_unit="ms")
    s = parse_table(text, "putty.log", fmt)
    assert np.allclose(s.field_ut, [[25.0, -12.5, 50.0], [26.0, -12.5, 50.0]])
    assert np.allclose(s.t_s, [1.0, 1.02])
    assert s.row.tolist() == [0, 1]  # no header: the first line is data row 0
    assert np.isnan(s.channels["col11"][0]) and s.channels["col11"][1] == 0.3
    assert "col7" not in s.channels and "col10" not in s.channels


@pytest.mark.parametrize("sep", [" ", "  ", "\t", ";"])
def test_three_bare_columns_are_x_y_z_whatever_the_separator(sep):
    # Magneto's input: three numbers per line, no header
    s = parse_table(sep.join(["1.5", "-2", "3e1"]) + "\n" + sep.join(["4", "5", "6"]) + "\n", "m.txt")
    assert s.field_ut.tolist() == [[1.5, -2.0, 30.0], [4.0, 5.0, 6.0]]


@pytest.mark.parametrize(
    "fmt, message",
    [
        (dict(columns=("mag_x", "mag_y")), "three columns"),
        (dict(columns=("mag_x", "mag_y", "mag_w")), "no magnetometer column 'mag_w'"),
        (dict(columns=("1", "2", "9")), "column 9 does not exist"),
        (dict(unit="furlongs"), "unknown field unit 'furlongs'"),
        (dict(unit="-0.3"), "positive"),
        (dict(time="clock"), "no time column 'clock'"),
        (dict(columns=("1", "2", "3"), time="3"), "different columns"),
        (dict(delimiter="::"), "one character"),
    ],
)
def test_asking_for_what_the_table_does_not_have_names_the_problem(fmt, message):
    with pytest.raises(InputError, match=message):
        parse_table("mag_x,mag_y,mag_z,t\n1,2,3,0\n", "rec.csv", TableFormat(**fmt))


def test_known_channels_are_taken_in_any_case():
    s = parse_table("t,mx,my,mz,Temp_C,current_A\n0,1,2,3,20,1.5\n", "r.csv")
    assert s.channels["temp_c"].tolist() == [20.0] and s.channels["current_a"].tolist() == [1.5]


def test_plausible_field_names_the_unit_that_would_fit():
    assert plausible_field(48.0) is None
    assert "gauss" in plausible_field(0.48) and "48.0 µT" in plausible_field(0.48)
    assert "mG" in plausible_field(480.0)
    assert "nT" in plausible_field(48000.0)
    assert "raw counts" in plausible_field(1730.0)
    assert "hardly turned" in plausible_field(2.8)  # no unit makes it one: a sphere wrapping a still cloud


def test_fit_warns_when_the_file_is_not_in_microtesla_and_reads_it_when_told(tmp_path, capsys):
    m_gauss = sphere_ut() / 100.0
    p = tmp_path / "gauss.csv"
    p.write_text("mag_x,mag_y,mag_z\n" + "\n".join(",".join(f"{v:.7f}" for v in r) for r in m_gauss) + "\n")
    assert main(["fit", str(p), "--model", "sphere", "--json"]) == 0
    out, err = capsys.readouterr()
    (d,) = json.loads(out)["fits"]
    assert d["calibration"]["field_ut"] == pytest.approx(0.48, rel=0.01)
    assert len(d["warnings"]) == 1 and "--unit gauss" in d["warnings"][0]
    assert d["input"] == "field from mag_x,mag_y,mag_z in µT (assumed: no unit given); no time column: sample index; no channels"
    assert "--unit gauss" in err
    assert main(["fit", str(p), "--model", "sphere", "--json", "--unit", "gauss"]) == 0
    (d,) = json.loads(capsys.readouterr().out)["fits"]
    assert d["calibration"]["field_ut"] == pytest.approx(48.0, rel=0.01)
    assert d["calibration"]["offset_ut"] == pytest.approx([12.0, -30.0, 7.0], abs=0.1)
    assert d["warnings"] == []
    assert d["input"].startswith("field from mag_x,mag_y,mag_z in gauss;")


def test_diagnose_and_export_take_the_same_table_options(tmp_path, capsys):
    m = sphere_ut(n=1200)
    p = tmp_path / "log.txt"
    p.write_text("\n".join(f"{i * 20} {r[0] / 100:.7f} {r[1] / 100:.7f} {r[2] / 100:.7f} 21.5"
                           for i, r in enumerate(m)) + "\n")
    opts = ["--columns", "2,3,4", "--unit", "gauss", "--time", "1", "--time-unit", "ms"]
    assert main(["diagnose", str(p), "--json", *opts]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["n_samples"] == 1200 and d["warnings"] == []
    assert d["calibration"]["field_ut"] == pytest.approx(48.0, rel=0.01)
    out = tmp_path / "log.csv"
    assert main(["export", str(p), "--csv", "-o", str(out), "--json", *opts]) == 0
    back = load_series(out)
    assert np.allclose(back.field_ut, m, atol=1e-5)
    assert back.t_s[1] == pytest.approx(0.02)
    assert back.channels["col5"][0] == 21.5


def test_table_options_on_a_capture_are_refused(tmp_path, capsys):
    cap = tmp_path / "run.cap"
    assert main(["record", "--port", "sim://?pace=0&seed=1", "-o", str(cap), "--count", "20"]) == 0
    capsys.readouterr()
    assert main(["fit", str(cap), "--unit", "gauss"]) == 6
    assert "not a table" in capsys.readouterr().err


def test_a_preamble_before_the_header_is_skipped():
    # a logger that writes its sample rate and settings before the column names
    s = parse_table("Fs,50.00\nInitialization time,60\nmx,my,mz\n6202,682,4812\n6177,682,4827\n", "q.csv")
    assert s.field_ut.tolist() == [[6202, 682, 4812], [6177, 682, 4827]]
    assert s.row.tolist() == [0, 1]


def test_prefixed_names_and_unnamed_columns():
    text = "unix_time,imu_mx,imu_my,imu_mz,imu_T,,\n1,55,1,-153,12.1,2,90\n2,64,-2,-155,11.9,3,91\n"
    s = parse_table(text, "board.csv")
    assert s.field_ut.tolist() == [[55, 1, -153], [64, -2, -155]]
    assert sorted(s.channels) == ["col6", "col7", "imu_T"] and s.t_s.tolist() == [1.0, 2.0]
    both = "imu_mx,imu_my,imu_mz,pni_mx,pni_my,pni_mz\n1,2,3,4,5,6\n"
    with pytest.raises(InputError, match="imu_mx,imu_my,imu_mz; pni_mx,pni_my,pni_mz"):
        parse_table(both, "board.csv")


def test_a_row_of_units_under_the_header_gives_the_units():
    s = parse_table("time,Bx,By,Bz,temp\nms,mG,mG,mG,degC\n0,100,200,300,21\n20,110,210,310,21\n", "u.csv")
    assert np.allclose(s.field_ut, [[10, 20, 30], [11, 21, 31]])
    assert np.allclose(s.t_s, [0.0, 0.02])
    assert s.row.tolist() == [0, 1] and s.channels["temp"].tolist() == [21, 21]


def test_temperature_and_current_columns_can_be_named_for_diagnosis():
    text = "t,mag_x,mag_y,mag_z,imu_T,I_motor,temp_c\n0,1,2,3,21.5,0.5,99\n1,1,2,3,21.7,1.5,99\n"
    s = parse_table(text, "b.csv", TableFormat(temp="imu_T", current="6"))
    assert s.channels["temp_c"].tolist() == [21.5, 21.7]  # the named column, not the old temp_c
    assert s.channels["current_a"].tolist() == [0.5, 1.5]
    assert "imu_T" not in s.channels and "I_motor" not in s.channels
    with pytest.raises(InputError, match="cannot be both"):
        parse_table(text, "b.csv", TableFormat(temp="mag_x"))
    with pytest.raises(InputError, match="holds text"):
        parse_table("mx,my,mz,label\n1,2,3,warm\n", "b.csv", TableFormat(temp="label"))


def test_a_second_magnetometer_is_not_a_covariate_and_channels_can_be_chosen():
    text = "t,imu_mx,imu_my,imu_mz,mag_x,mag_y,mag_z,temp,enviro_h\n0,1,2,3,4,5,6,20,40\n1,1,2,3,4,5,6,21,41\n"
    s = parse_table(text, "two.csv", TableFormat(columns=("imu_mx", "imu_my", "imu_mz")))
    assert sorted(s.channels) == ["enviro_h", "temp"]
    s = parse_table(text, "two.csv", TableFormat(columns=("mag_x", "mag_y", "mag_z"), channels=("enviro_h",)))
    assert s.field_ut.tolist()[0] == [4, 5, 6] and list(s.channels) == ["enviro_h"]
    s = parse_table(text, "two.csv", TableFormat(columns=("mag_x", "mag_y", "mag_z"), channels=()))
    assert s.channels == {}
    with pytest.raises(InputError, match="no channel column 'humidity'"):
        parse_table(text, "two.csv", TableFormat(columns=("2", "3", "4"), channels=("humidity",)))


def test_diagnose_suggests_choosing_channels_in_a_wide_log():
    from magcal.cli.diagnose import many_channels_hint

    quiet = {"findings": [{"effect": "outliers"}]}
    assert "--channels" in many_channels_hint(20, quiet)
    assert many_channels_hint(3, quiet) is None
    assert many_channels_hint(20, {"findings": [{"effect": "temperature_drift"}]}) is None


from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_cells = st.sampled_from(["mx", "my", "mz", "mag_x", "mag_y", "mag_z", "t", "time_ms", "temp_c", "1", "-2.5",
                          "nan", "", "abc", "uT", "gauss", "1e400", "0x10", " ", '"3,4"', "#", "valid"])
_lines = st.lists(st.lists(_cells, min_size=1, max_size=6).map(lambda cs: st_join(cs)), min_size=0, max_size=8)


def st_join(cells):
    return cells[0] if len(cells) == 1 else ("," if len(cells) % 2 else "\t").join(cells)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(_lines, st.sampled_from([None, ("1", "2", "3"), ("mag_x", "my", "3")]), st.sampled_from([None, "gauss", "0.3"]))
def test_any_text_is_read_or_refused_with_a_named_problem(lines, columns, unit):
    text = "\n".join(lines) + "\n"
    try:
        s = parse_table(text, "fuzz.csv", TableFormat(columns=columns, unit=unit))
    except InputError as exc:
        assert "fuzz.csv" in str(exc) or "--columns" in str(exc) or "unit" in str(exc)
        return
    assert s.field_ut.shape == (len(s), 3) and np.all(np.isfinite(s.field_ut))



def test_matlab_and_other_binary_files_are_named_as_such(tmp_path):
    mat = tmp_path / "log.mat"
    mat.write_bytes(b"MATLAB 5.0 MAT-file, Platform: PCWIN64" + bytes(range(256)))
    with pytest.raises(InputError, match="MATLAB .mat file.*writematrix"):
        load_series(mat)
    blob = tmp_path / "log.bin"
    blob.write_bytes(b"\x7fELF\x02\x01\x01\x00" + bytes(200))
    with pytest.raises(InputError, match="a binary file"):
        load_series(blob)


def test_a_table_wider_than_any_magnetometer_log_is_refused_by_name(tmp_path):
    """Width was quadratic (80 000 columns: 73 s); now more than 10 000 columns is refused at once."""
    path = tmp_path / "wide.csv"
    path.write_text(",".join(f"c{i}" for i in range(12_000)) + "\n" + ",".join("1.5" for _ in range(12_000)) + "\n")
    with pytest.raises(InputError, match=r"wide.csv line 1: 12000 columns, more than 10000"):
        load_series(path, TableFormat(columns=("1", "2", "3")))


def test_a_line_of_megabytes_is_refused_by_name(tmp_path):
    path = tmp_path / "one.csv"
    path.write_text(",".join("1.5" for _ in range(600_000)) + "\n")  # 2.4 MB in one line
    with pytest.raises(InputError, match=r"one.csv line 1: 2399999 characters in one line"):
        load_series(path, TableFormat(columns=("1", "2", "3")))


def test_a_table_is_read_as_a_stream_of_lines():
    """The reader takes any iterator of lines and reads it once, in blocks: it never needs the
    whole file in memory (a 3 M-row file: bench/scale.py)."""
    from magcal.recordings.table import BLOCK_ROWS, read_table

    n = 2 * BLOCK_ROWS + 7
    taken = []

    def lines():
        yield "t,mx,my,mz"
        for i in range(n):
            taken.append(i)
            yield f"{i * 0.01},{i % 50},{-i % 30},{i % 7}"

    s = read_table(lines(), "gen.csv")
    assert len(s) == n and len(taken) == n and s.field_ut[-1].tolist() == [float((n - 1) % 50), float(-(n - 1) % 30),
                                                                             float((n - 1) % 7)]


def test_a_long_recording_is_fitted_on_every_kth_sample_and_says_so(tmp_path, capsys, monkeypatch):
    """Memory stays bounded whatever the length (bench/scale.py: 3 M rows); the fit says which
    samples it used, and its outliers still point at the file's own samples."""
    import magcal.cli.fit as fit_cli

    monkeypatch.setattr(fit_cli, "MAX_FIT_SAMPLES", 500)
    m = sphere_ut(2000, seed=5)
    m[[8, 400, 1204]] += 30.0  # three jumps, on samples the thinning keeps (every 4th)
    path = tmp_path / "long.csv"
    path.write_text("mx,my,mz\n" + "".join(f"{a},{b},{c}\n" for a, b, c in m))
    assert main(["fit", str(path), "--json", "--model", "sphere"]) == 0
    out, err = capsys.readouterr()
    (d,) = json.loads(out)["fits"]
    assert d["reading"]["thinned_every"] == 4 and d["reading"]["samples_read"] == 2000 and d["n_samples"] == 2000
    assert d["n_used"] <= 500 and {8, 400, 1204} <= set(d["outliers"]) and all(i % 4 == 0 for i in d["outliers"])
    assert "the fit uses every 4th sample (500 of 2000" in err
    assert main(["fit", str(path), "--model", "sphere"]) == 0  # the text says so too
    assert "thinned     every 4th sample of 2000" in capsys.readouterr().out


def test_a_thinned_fit_reports_the_uncertainty_of_the_samples_it_fitted(tmp_path, capsys, monkeypatch):
    """Honest ± : a fit of every 4th sample claims the precision of those samples (about twice
    the 1σ of a fit of all of them), exactly what fitting those samples alone reports."""
    import magcal.cli.fit as fit_cli

    m = sphere_ut(4000, seed=6)
    whole, kth = tmp_path / "whole.csv", tmp_path / "kth.csv"
    whole.write_text("mx,my,mz\n" + "".join(f"{a},{b},{c}\n" for a, b, c in m))
    kth.write_text("mx,my,mz\n" + "".join(f"{a},{b},{c}\n" for a, b, c in m[::4]))

    def sigma(path) -> tuple[np.ndarray, float, float, np.ndarray]:
        assert main(["fit", str(path), "--json", "--model", "sphere", "--no-outliers"]) == 0
        (d,) = json.loads(capsys.readouterr().out)["fits"]
        u = d["uncertainty"]
        return np.array(u["offset_ut"]), u["direction_factor"], u["time_block_factor"], np.array(d["crlb_offset_ut"])

    full, full_widened, _, full_precision = sigma(whole)
    monkeypatch.setattr(fit_cli, "MAX_FIT_SAMPLES", 1000)
    thinned, thinned_widened, thinned_by_time, _ = sigma(whole)
    np.testing.assert_allclose(thinned, sigma(kth)[0], rtol=1e-9)
    # never the precision of samples it did not fit (the full fit's own σ may be widened by its
    # time blocks' jackknife, so the bound is on the precision all the samples would give)
    assert np.all(thinned > 1.6 * full_precision), (thinned, full_precision)
    # beyond √4, only what the thinned fit states: its direction widening, whose excess comes
    # from six faces (Student's t with 5 degrees of freedom: 2.571 / 1.96), and its time blocks'
    ratio = thinned / full
    assert np.all(ratio < 2.5 * thinned_widened / full_widened * 2.571 / 1.96 * thinned_by_time), (ratio, thinned_widened)


def test_a_plain_first_block_is_read_at_once_with_the_same_values_and_text_columns(monkeypatch):
    """The first block of rows is read at once when it is plain numbers, its text columns decided
    by the first data row as line by line: the same samples, channels and text columns either
    way, and a bad cell further down still named by its line."""
    import magcal.recordings.table as table

    m = sphere_ut(300)
    rows = [f"{i * 0.01:.2f},{'on' if i % 2 else 'off'},{x:.6g},{y:.6g},{z:.6g},{20 + i * 1e-3:.4e}"
            for i, (x, y, z) in enumerate(m)]
    text = "t_s,state,mx_ut,my_ut,mz_ut,temp_c\n" + "\n".join(rows) + "\n"
    fast = parse_table(text, "r.csv", TableFormat(delimiter=","))
    monkeypatch.setattr(table, "_plain_block", lambda *a: None)  # every block line by line
    slow = parse_table(text, "r.csv", TableFormat(delimiter=","))
    monkeypatch.undo()
    assert np.array_equal(fast.field_ut, slow.field_ut) and np.array_equal(fast.t_s, slow.t_s)
    assert set(fast.channels) == set(slow.channels) == {"temp_c"}
    assert np.array_equal(fast.channels["temp_c"], slow.channels["temp_c"])
    bad = text.replace(rows[200], rows[200].replace(f"{m[200][1]:.6g}", "1.2.3"))
    with pytest.raises(InputError, match=r"r\.csv line 202: column 'my_ut': '1\.2\.3' is not a number"):
        parse_table(bad, "r.csv", TableFormat(delimiter=","))
