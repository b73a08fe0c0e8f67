"""The bundle CSV reader's C fast path (Arrow's CSV reader) and its general path agree.

``read_csv_table`` tries Arrow first and falls back to the csv module for anything it does not
accept. Each file below is read both ways (the general path by forcing the fallback): the
columns, the text columns and the line numbers (which error messages and the report quote) must
be the same -- a blank or comment line skipped silently by the fast path would shift every line
number after it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from koala_bridge.calibration import bundle
from koala_bridge.calibration.bundle import BundleError, read_csv_table

CASES = {
    "plain": "t,a\n0,1\n0.5,2\n1,3\n",
    "crlf": "t,a\r\n0,1\r\n0.5,2\r\n",
    "no final newline": "t,a\n0,1\n1,2",
    "trailing blank lines": "t,a\n0,1\n1,2\n\n\n",
    "blank line inside": "t,a\n0,1\n\n1,2\n",
    "whitespace line inside": "t,a\n0,1\n   \n1,2\n",
    "comment line": "t,a\n0,1\n# pause\n1,2\n",
    "empty cell": "t,a\n0,\n1,2\n",
    "quoted number": 't,a\n0,"1"\n1,2\n',
    "text column": "t,name\n0,left\n1,right\n",
    "nan cell": "t,a\n0,nan\n1,2\n",
    "spaces around cells": "t , a\n0 , 1\n 1, 2\n",
    "one row": "t,a\n0,1\n",
    "one column": "t\n0\n1\n2\n",
    "signs, exponents, bare points": "t,a\n+1,1e-3\n.5,-2.E+2\n1.,-0\n2,1E5\n",
    "digits with underscores": "t,a\n0,1_000\n1,2\n",
    "NaN capitalised": "t,a\n0,NaN\n1,2\n",
    "hex": "t,a\n0,0x10\n1,2\n",
    "byte order mark": "\ufefft,a\n0,1\n1,2\n",
    "tab around a number": "t,a\n0,\t1\n1,2\n",
    # Arrow's first line ends at the CR, the header's at the LF: columns 't\r0' and '1' were read
    "lone CR in the header line": "t\r0\n1\n2\n",
    "CR-only line ends": "t,a\r0,1\r1,2\r",
}


def _slow(monkeypatch: pytest.MonkeyPatch, path: Path) -> bundle.Table:
    with monkeypatch.context() as m:
        m.setattr(bundle, "_read_numeric_fast", lambda *_: None)
        return read_csv_table(path)


@pytest.mark.parametrize("name", sorted(CASES))
def test_fast_and_general_readers_agree(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "gyro.csv"
    path.write_text(CASES[name], encoding="utf-8", newline="")
    fast, slow = read_csv_table(path), _slow(monkeypatch, path)
    assert fast.columns.keys() == slow.columns.keys()
    for k in fast.columns:
        np.testing.assert_array_equal(fast.columns[k], slow.columns[k])
    assert fast.text.keys() == slow.text.keys()
    np.testing.assert_array_equal(fast.lines, slow.lines)


def _general_reader_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object, **__: object) -> None:
        raise AssertionError("the general reader read a plain numeric file")

    monkeypatch.setattr(bundle.csv, "reader", refuse)


def test_a_plain_numeric_file_is_read_by_the_fast_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The agreement above holds trivially if the fast path never answers: a plain file, and
    one of several of Arrow's blocks, must not reach the csv module."""
    _general_reader_refused(monkeypatch)
    rng = np.random.default_rng(3)
    values = rng.normal(size=(60_000, 3))  # ~3 MB: more than one of Arrow's 1 MB blocks
    path = tmp_path / "gyro.csv"
    np.savetxt(path, values, delimiter=",", header="t,a,b", comments="", fmt="%.17g")
    table = read_csv_table(path)
    for i, k in enumerate(("t", "a", "b")):
        np.testing.assert_array_equal(table.columns[k], values[:, i])  # the same bits
        assert table.columns[k].flags.writeable
    np.testing.assert_array_equal(table.lines, np.arange(2, 60_002))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(allow_nan=False, allow_infinity=False, min_value=-1e12, max_value=1e12),
            st.integers(min_value=-(10**12), max_value=10**12),
        ),
        min_size=1,
        max_size=30,
    ),
    st.sampled_from(["{!r}", "{:.6g}", "{:.17e}", "{:f}"]),
)
def test_numbers_as_loggers_write_them_read_to_the_same_bits(
    rows: list[tuple[float, int]], fmt: str
) -> None:
    """Both paths parse a number correctly rounded: the same float64, bit for bit, whatever
    the logger's format (repr, %g, %e, %f, integers)."""
    import tempfile

    text = "t,a\n" + "".join(f"{fmt.format(x)},{n}\n" for x, n in rows)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "gyro.csv"
        path.write_text(text, encoding="utf-8")
        fast = read_csv_table(path)
        with pytest.MonkeyPatch.context() as m:
            m.setattr(bundle, "_read_numeric_fast", lambda *_: None)
            slow = read_csv_table(path)
    for k in ("t", "a"):
        assert fast.columns[k].tobytes() == slow.columns[k].tobytes()


def test_the_line_after_a_blank_line_is_numbered_as_in_the_file(tmp_path: Path) -> None:
    path = tmp_path / "gyro.csv"
    path.write_text("t,a\n0,1\n\n1,1e300\n", encoding="utf-8")
    with pytest.raises(BundleError, match="line 4"):
        read_csv_table(path)


def test_a_row_of_another_width_is_named_by_its_line(tmp_path: Path) -> None:
    path = tmp_path / "gyro.csv"
    path.write_text("t,a\n0,1\n1,2,3\n", encoding="utf-8")
    with pytest.raises(BundleError, match="line 3: 3 cell"):
        read_csv_table(path)


@pytest.mark.parametrize(("data", "where"), [
    (b"t,a\n0,1\n1,\xe92\n", "line 3: not UTF-8"),  # invalid in the body, no NUL byte
    (b"t,\xe9\n0,1\n", "line 1: not UTF-8"),  # in the header
    (b"t,a\n0,1\n1,2\x00\n", "line 3: a NUL byte"),
])
def test_bytes_the_fast_path_does_not_decode_are_named_by_line(
    data: bytes, where: str, tmp_path: Path
) -> None:
    """The fast path reads the file's bytes without decoding them (numpy decodes): what is not
    UTF-8 text, or holds a NUL, still reaches the general reader and is named by its line."""
    path = tmp_path / "gyro.csv"
    path.write_bytes(data)
    with pytest.raises(BundleError, match=where):
        read_csv_table(path)
