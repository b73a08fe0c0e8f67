"""Property-based fuzzing (hypothesis) of the socketcand element parser (drivers/transports/
socketcand.py), in the style of test_fuzz_decoders.py.

- :func:`parse_send_element` turns the words of any text into a ``can.Message`` or a reason
  string, never raises; a valid ``< send ID DLC BYTES >`` round-trips, and a mutated one still
  ends in one of the two documented results;
- the server's stream parser (``< ... >`` splitting, per-element dispatch) fed arbitrary bytes and
  mutated elements on a live loopback connection neither raises nor closes the connection: a
  valid ``< send >`` after the garbage still reaches the bus.
"""

from __future__ import annotations

import socket

import can
import pytest
from _socketcand_client import read_element
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from koala_bridge.drivers.transports.socketcand import SocketcandServer, parse_send_element

pytestmark = pytest.mark.timeout(120)

FUZZ = settings(
    max_examples=200,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

CHANNEL = "koala0"


@st.composite
def can_messages(draw: st.DrawFn) -> can.Message:
    extended = draw(st.booleans())
    can_id = draw(st.integers(0, 0x1FFFFFFF if extended else 0x7FF))
    data = draw(st.binary(max_size=8))
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=data)


def send_element(msg: can.Message) -> str:
    """``< send ID DLC B0 ... >`` as python-can's socketcand interface writes it."""
    can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    data = " ".join(f"{b:02X}" for b in msg.data)
    return f"< send {can_id} {msg.dlc:X} {data} >"


def _words(element: str) -> list[str]:
    return element.strip().strip("<>").split()


def _check_result(result: object) -> None:
    assert isinstance(result, (can.Message, str))
    if isinstance(result, can.Message):
        assert 0 <= result.arbitration_id <= 0x1FFFFFFF
        assert len(result.data) <= 8


@FUZZ
@given(st.text(max_size=200))
def test_parse_send_element_takes_any_text(text: str) -> None:
    _check_result(parse_send_element(["send", *text.split()]))
    _check_result(parse_send_element(text.split() or ["send"]))


@FUZZ
@given(can_messages())
def test_a_valid_send_element_round_trips(msg: can.Message) -> None:
    got = parse_send_element(_words(send_element(msg)))
    assert isinstance(got, can.Message), got
    assert (got.arbitration_id, got.is_extended_id, bytes(got.data)) == (
        msg.arbitration_id, msg.is_extended_id, bytes(msg.data))


@FUZZ
@given(can_messages(), st.data())
def test_a_mutated_send_element_is_a_message_or_a_reason(msg: can.Message, data: st.DataObject
                                                         ) -> None:
    text = send_element(msg)
    pos = data.draw(st.integers(0, len(text) - 1))
    kind = data.draw(st.sampled_from(["replace", "delete", "insert", "truncate"]))
    char = data.draw(st.characters())
    if kind == "replace":
        text = text[:pos] + char + text[pos + 1 :]
    elif kind == "delete":
        text = text[:pos] + text[pos + 1 :]
    elif kind == "insert":
        text = text[:pos] + char + text[pos:]
    else:
        text = text[:pos]
    _check_result(parse_send_element(_words(text)))


def _mutated_elements() -> st.SearchStrategy[bytes]:
    valid = st.sampled_from([b"< send 123 1 AB >", b"< echo >", b"< rawmode >", b"< bcmmode >",
                             b"< open koala0 >", b"< send 1FFFFFFF 8 0 1 2 3 4 5 6 7 >"])
    mutated = st.tuples(valid, st.integers(0, 40), st.binary(max_size=4)).map(
        lambda t: t[0][: t[1]] + t[2] + t[0][t[1] :])
    return st.lists(st.one_of(valid, mutated, st.binary(max_size=64)), max_size=8).map(b"".join)


def test_the_stream_parser_survives_any_bytes() -> None:
    with SocketcandServer(channel=CHANNEL, max_clients=256, handshake_timeout_s=60.0) as server:

        @FUZZ
        @given(_mutated_elements())
        def feed(garbage: bytes) -> None:
            with socket.create_connection((server.endpoint.host, server.endpoint.port), 10) as s:
                assert read_element(s) == b"< hi >"
                s.sendall(f"< open {CHANNEL} >< rawmode >".encode())
                assert read_element(s) == b"< ok >"
                assert read_element(s) == b"< ok >"
                s.sendall(garbage)
                # ">" ends an element the garbage left open; then a valid frame must still land
                # (the connection stayed open and the parser found the next element).
                s.sendall(b" >< send 7A5 2 C0 DE >")
                while True:
                    got = server.recv(10.0)
                    assert got is not None, f"no frame after {garbage!r}"
                    if (got.arbitration_id, bytes(got.data)) == (0x7A5, b"\xc0\xde"):
                        break

        feed()
