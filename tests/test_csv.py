"""CSV in and out: the columns a user writes, the errors a user sees, exact round trips."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from magcal.app.load import load_series
from magcal.cli import main
from magcal.core.errors import InputError
from magcal.core.series import Series
from magcal.recordings.table import load_csv, parse_csv, save_csv


def write(tmp_path, text, name="in.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_required_optional_and_auxiliary_columns(tmp_path):
    p = write(tmp_path, "t,mx,my,mz,temp_c,current_a,label\n0.0,1,2,3,25.5,0.1,a\n0.5,4,5,6,25.75,,b\n")
    s = load_series(p)
    assert s.t_s.tolist() == [0.0, 0.5]
    assert s.field_ut.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert s.channels["temp_c"].tolist() == [25.5, 25.75]
    assert s.channels["current_a"][0] == 0.1 and np.isnan(s.channels["current_a"][1])
    assert "label" not in s.channels  # a text column is not a channel


def test_time_is_optional_and_column_order_free(tmp_path):
    s = load_series(write(tmp_path, "mz,mx,my\n3,1,2\n6,4,5\n9,7,8\n"))
    assert s.field_ut.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert s.t_s.tolist() == [0.0, 1.0, 2.0]  # the sample index when no t column


def test_row_is_the_data_row_in_the_file(tmp_path):
    text = "# a comment\nt,mx,my,mz\n0,1,1,1\n\n1,2,2,2\n# note\n2,3,3,3\n"
    s = load_series(write(tmp_path, text))
    # data rows counted from the line after the header: blank and comment lines keep their place
    assert s.row.tolist() == [0, 2, 4]
    lines = text.splitlines()
    for r, f in zip(s.row, s.field_ut):
        assert float(lines[2 + r].split(",")[1]) == f[0]
    sub = s.take(np.array([2]))
    assert sub.row.tolist() == [4]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("\n\n", "empty"),
        ("t,mx,my,mz\n", "no data rows"),
        ("t,mx,my\n0,1,2\n", "lacks column.*mz"),
        ("t,x,y,z\n0,1,2,3\n", "mx, my, mz"),
        ("t,mx,my,mz\n0,1,2,3\n1,1,abc,3\n", r"line 3: column 'my': 'abc' is not a number"),
        ("t,mx,my,mz\n0,1,,3\n", "line 2: column 'my': is empty"),
        ("t,mx,my,mz\n0,1,2\n", "line 2: 3 values, the header has 4"),
        ("t,mx,my,mz,temp_c\n0,1,2,3,20\n1,1,2,3,hot\n", r"line 3: column 'temp_c': 'hot'"),
        ("t,mx,my,mz\n0,1,2,inf\n", "not finite"),
        ("t,mx,mx,my,mz\n0,1,1,2,3\n", "duplicate"),
    ],
)
def test_bad_input_names_file_line_and_problem(tmp_path, text, message):
    p = write(tmp_path, text, "bad.csv")
    with pytest.raises(InputError, match=message) as exc:
        load_csv(p)
    assert "bad.csv" in str(exc.value)


def test_missing_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="nothere.csv"):
        load_series(tmp_path / "nothere.csv")


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 30), st.just(5)), elements=finite), st.lists(st.booleans(), min_size=30, max_size=30))
def test_save_then_load_is_bit_exact(tmp_path_factory, a, flags):
    n = len(a)
    s = Series(t_s=a[:, 0], field_ut=a[:, 1:4], channels={"temp_c": a[:, 4], "current_a": a[:, 0] * 0.5},
               valid=np.array(flags[:n]))
    p = tmp_path_factory.mktemp("csv") / "s.csv"
    save_csv(s, p)
    back = load_series(p)
    assert np.array_equal(back.t_s, s.t_s) and np.array_equal(back.field_ut, s.field_ut)
    assert np.array_equal(back.channels["temp_c"], s.channels["temp_c"])
    assert np.array_equal(back.channels["current_a"], s.channels["current_a"])
    assert np.array_equal(back.valid, s.valid)


def test_export_command_writes_the_documented_columns(tmp_path, capsys):
    # a timed source (an untimed one is exported without t: tests/test_assumed_truths.py)
    src = write(tmp_path, "t,mx,my,mz,temp_c\n0,1,2,3,20\n1,4,5,6,21\n", "rec.csv")
    out = tmp_path / "out.csv"
    assert main(["export", str(src), "--csv", "-o", str(out)]) == 0
    header, *rows = out.read_text().splitlines()
    assert header == "t,mx,my,mz,temp_c"
    assert rows == ["0.0,1.0,2.0,3.0,20.0", "1.0,4.0,5.0,6.0,21.0"]
    assert main(["export", str(src), "--csv", "-o", str(src)]) == 6  # never overwrites its input
    assert "refusing" in capsys.readouterr().err


def test_parse_csv_accepts_a_byte_order_mark_and_spaces(tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes("\ufeff t , mx , my , mz \n 0 , 1 , 2 , 3 \n".encode("utf-8"))
    assert load_series(p).field_ut.tolist() == [[1, 2, 3]]
    assert parse_csv("mx,my,mz\n1,2,3\n").field_ut.tolist() == [[1, 2, 3]]
