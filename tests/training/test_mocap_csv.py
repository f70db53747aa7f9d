"""Mocap CSV: bit-exact round trips (hypothesis), error messages with file/line/column, Motion save/load."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from torchpf.io import MocapFormatError, read_mocap_csv, write_mocap_csv
from training.mocap import Motion, load_csv, save_csv

NAME = st.text(
    alphabet=st.characters(codec="utf-8", exclude_characters=',"\r\n', exclude_categories=("Cs", "Cc", "Z")),
    min_size=1,
    max_size=12,
).filter(lambda s: s != "time" and s == s.strip())


@st.composite
def tables(draw):
    names = draw(st.lists(NAME, min_size=1, max_size=6, unique=True))
    T = draw(st.integers(0, 12))
    # Any finite float64: subnormals, -0.0, +-1.8e308.
    values = draw(
        hnp.arrays(np.float64, (T, len(names)), elements=st.floats(allow_nan=False, allow_infinity=False))
    )
    times = None
    if draw(st.booleans()):
        start = draw(st.floats(-1e6, 1e6))
        steps = draw(hnp.arrays(np.float64, (T,), elements=st.floats(1e-6, 1e3)))
        times = start + np.cumsum(steps)
        if T > 1 and np.any(np.diff(times) <= 0):  # steps lost to rounding at this magnitude
            times = None
    return names, times, values


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(table=tables(), crlf=st.booleans())
def test_csv_round_trip_is_bit_exact(tmp_path, table, crlf):
    names, times, values = table
    path = tmp_path / "m.csv"
    write_mocap_csv(path, names, values, times=times)
    if crlf:
        path.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))
    got_names, got_times, got_values = read_mocap_csv(path)
    assert got_names == names
    assert _same_bits(got_values, values)
    assert (got_times is None) == (times is None)
    if times is not None:
        assert _same_bits(got_times, times)
    # Reading against a shuffled expected list returns that order.
    order = list(reversed(names))
    n2, _, v2 = read_mocap_csv(path, expected_dof_names=order)
    assert n2 == order and _same_bits(v2, values[:, ::-1].copy())


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    angles=hnp.arrays(
        np.float64, st.tuples(st.integers(1, 20), st.integers(1, 5)), elements=st.floats(-10, 10)
    ),
    fps=st.floats(1, 1000),
)
def test_motion_round_trip(tmp_path, angles, fps):
    motion = Motion([f"d{i}" for i in range(angles.shape[1])], fps, torch.from_numpy(angles), name="m")
    save_csv(tmp_path / "m.csv", motion)
    back = load_csv(tmp_path / "m.csv", fps=None if len(angles) > 1 else fps)
    assert back.dof_names == motion.dof_names and back.name == "m"
    assert torch.equal(back.angles, motion.angles)
    assert back.fps == pytest.approx(fps, rel=1e-9)


# ------------------------------------------------------------------------------------------------ errors
def _read_error(tmp_path, text: str, expected=None) -> MocapFormatError:
    path = tmp_path / "bad.csv"
    path.write_bytes(text.encode())
    with pytest.raises(MocapFormatError) as info:
        read_mocap_csv(path, expected_dof_names=expected)
    assert str(info.value).startswith(f"{path}:")
    return info.value


@pytest.mark.parametrize(
    ("text", "line", "column", "words"),
    [
        ("", 1, None, "empty file"),
        ("\n\n", 1, None, "empty file"),
        ("time,a,b\n0,1,2\n1,1,x\n", 3, "3 ('b')", "not a number: 'x'"),
        ("a,b\n1,nan\n", 2, "2 ('b')", "finite, got 'nan'"),
        ("a,b\n1,-inf\n", 2, "2 ('b')", "finite, got '-inf'"),
        ("a,b\n1,1e999\n", 2, "2 ('b')", "finite"),
        ("a,b\n1,\n", 2, "2 ('b')", "not a number: ''"),
        ("a,b\n1,2,3\n", 2, None, "expected 2 fields, got 3 fields"),
        ("a,b\n1\n", 2, None, "expected 2 fields, got 1 fields"),
        ("a,b\n1,2\n\n3,4\n", 3, None, "empty line"),
        ("a,b,a\n1,2,3\n", 1, "3 ('a')", "duplicate column name (also column 1)"),
        ("a,,b\n1,2,3\n", 1, "2", "empty column name"),
        ("a,time\n1,2\n", 1, "2 ('time')", "must be the first column"),
        ("time,a\n0,1\n0,2\n", 3, "1 ('time')", "strictly increasing"),
    ],
)
def test_read_errors_name_line_and_column(tmp_path, text, line, column, words):
    err = _read_error(tmp_path, text)
    assert (err.line, err.column) == (line, column), str(err)
    assert words in str(err)


def test_columns_checked_against_expected(tmp_path):
    err = _read_error(tmp_path, "time,a,b,zz\n0,1,2,3\n", expected=["a", "b", "c"])
    assert err.line == 1 and err.column == "4 ('zz')"
    assert "unknown column(s) ['zz']" in str(err) and "missing column(s) ['c']" in str(err)
    err = _read_error(tmp_path, "a\n0\n", expected=["a", "b"])
    assert "missing column(s) ['b']" in str(err)


def test_header_only_bom_crlf_and_whitespace(tmp_path):
    path = tmp_path / "h.csv"
    path.write_bytes("\ufefftime, a ,b\r\n".encode())
    names, times, values = read_mocap_csv(path)
    assert names == ["a", "b"] and times.shape == (0,) and values.shape == (0, 2)
    path.write_text("a,b\n 1.5 , -2e-3 \n\n\n")
    _, times, values = read_mocap_csv(path)
    assert times is None and values.tolist() == [[1.5, -0.002]]


@pytest.mark.parametrize(
    ("names", "values", "times", "words"),
    [
        (["a", "a"], np.zeros((1, 2)), None, "duplicate"),
        (["a,b"], np.zeros((1, 1)), None, "commas"),
        ([" a"], np.zeros((1, 1)), None, "whitespace"),
        (["time"], np.zeros((1, 1)), None, "reserved"),
        (["a"], np.zeros((2, 2)), None, r"shape \(T, 1\)"),
        (["a", "b"], np.array([[0.0, np.nan]]), None, r"values\[0, 1\] \('b'\) is nan"),
        (["a"], np.zeros((2, 1)), [0.0, 0.0], "strictly increasing"),
        (["a"], np.zeros((2, 1)), [0.0], r"shape \(2,\)"),
    ],
)
def test_write_rejects_bad_input_and_keeps_old_file(tmp_path, names, values, times, words):
    path = tmp_path / "w.csv"
    path.write_text("old")
    with pytest.raises(ValueError, match=words):
        write_mocap_csv(path, names, values, times=times)
    assert path.read_text() == "old"


def test_write_accepts_tensors(tmp_path):
    path = tmp_path / "t.csv"
    write_mocap_csv(path, ["a"], torch.tensor([[0.1]], dtype=torch.float32), times=torch.tensor([2.0]))
    assert path.read_text() == f"time,a\n2.0,{float(np.float32(0.1))!r}\n"


# ------------------------------------------------------------------------------------------------ load_csv
def test_load_csv_frame_rate_rules(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("a\n1\n2\n")
    with pytest.raises(ValueError, match="no time column.*pass fps"):
        load_csv(path)
    assert load_csv(path, fps=30).fps == 30.0
    path.write_text("time,a\n5.0,1\n")
    with pytest.raises(ValueError, match="single frame"):
        load_csv(path)
    path.write_text("time,a\n0.1,1\n0.2,2\n0.3,3\n")
    assert load_csv(path).fps == pytest.approx(10.0)
    assert load_csv(path, fps=10.0).fps == pytest.approx(10.0)
    with pytest.raises(ValueError, match="disagrees"):
        load_csv(path, fps=12)


def test_load_csv_non_uniform_times(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("time,a\n0.0,1\n0.1,2\n0.25,3\n0.3,4\n")
    with pytest.raises(MocapFormatError, match="not uniform") as info:
        load_csv(path)
    assert (info.value.line, info.value.column) == (4, "1 ('time')")  # the row of 0.25: a 0.15 s step


def test_load_csv_against_skeleton_dofs(tmp_path):
    path = tmp_path / "m.csv"
    save_csv(path, Motion(["b", "a"], 100, torch.tensor([[2.0, 1.0], [4.0, 3.0]])))
    m = load_csv(path, dof_names=["a", "b"])
    assert m.dof_names == ["a", "b"] and m.angles.tolist() == [[1.0, 2.0], [3.0, 4.0]]
    with pytest.raises(MocapFormatError, match=r"unknown column\(s\) \['b'\]"):
        load_csv(path, dof_names=["a", "c"])


@pytest.mark.parametrize(
    ("field", "words"),
    [("1_000", "not a plain decimal number: '1_000'"), ("\u0661\u0662", "not a plain decimal number")],
)
def test_csv_refuses_numbers_a_formatter_does_not_write(tmp_path, field, words):
    path = tmp_path / "m.csv"
    path.write_text(f"time,a,b\n0.0,1.0,2.0\n0.1,{field},2.0\n", encoding="utf-8")
    with pytest.raises(MocapFormatError, match=words) as info:
        read_mocap_csv(path)
    assert (info.value.line, info.value.column) == (3, "2 ('a')")


def test_csv_errors_print_plain_numbers(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("time,a\n0.0,1.0\n0.0333,1.0\n0.1,1.0\n")
    with pytest.raises(MocapFormatError) as info:
        load_csv(path)
    assert "np.float64" not in str(info.value) and "0.0333" in str(info.value)
    path.write_text("time,a\n0.0,1.0\n0.0,1.0\n")
    with pytest.raises(MocapFormatError, match=r"\(0.0 then 0.0\)"):
        read_mocap_csv(path)


def test_load_csv_refuses_absurd_values(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("time,a,b\n0.0,1.0,2.0\n0.1,1.0,1e300\n")
    with pytest.raises(MocapFormatError, match="at most 1e\\+06 rad or m, got 1e\\+300") as info:
        load_csv(path)
    assert info.value.line == 3 and "m.csv" in str(info.value)
