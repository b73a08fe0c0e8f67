"""K-Team ASCII codec, and the codec served on a real pty to a pyserial client."""

from __future__ import annotations

import random
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from koala_bridge.drivers.kteam import (
    ERROR_OUT_OF_RANGE,
    ERROR_PROTOCOL,
    ERROR_UNKNOWN_COMMAND,
    KteamLimits,
    LineSplitter,
    command_specs,
    error_reply,
    format_command,
    format_reply,
    parse_command,
    parse_reply,
)
from koala_bridge.drivers.messages import FrameError, KteamCommand, KteamReply, Reject, RejectReason
from koala_bridge.drivers.transports.pty import PtyTransport

# --------------------------------------------------------------------------- codec


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b"B", KteamCommand("B")),
        (b"D,10,-10", KteamCommand("D", (10, -10))),
        (b"D, +127 , -127", KteamCommand("D", (127, -127))),
        (b"E", KteamCommand("E")),
        (b"G,-2147483648,2147483647", KteamCommand("G", (-(2**31), 2**31 - 1))),
        (b"H", KteamCommand("H")),
        (b"N", KteamCommand("N")),
        (b"O", KteamCommand("O")),
        (b"L,1,2", KteamCommand("L", (1, 2))),
    ],
)
def test_parse_valid_commands(line: bytes, expected: KteamCommand) -> None:
    assert parse_command(line) == expected


@pytest.mark.parametrize(
    ("line", "reason", "text"),
    [
        (b"X", RejectReason.UNKNOWN_COMMAND, ERROR_UNKNOWN_COMMAND),
        (b"d,1,1", RejectReason.UNKNOWN_COMMAND, ERROR_UNKNOWN_COMMAND),
        (b"", RejectReason.SYNTAX, ERROR_PROTOCOL),
        (b"D,1", RejectReason.ARITY, ERROR_PROTOCOL),
        (b"D,1,2,3", RejectReason.ARITY, ERROR_PROTOCOL),
        (b"H,1", RejectReason.ARITY, ERROR_PROTOCOL),
        (b"D,a,1", RejectReason.SYNTAX, ERROR_PROTOCOL),
        (b"D,1.5,1", RejectReason.SYNTAX, ERROR_PROTOCOL),
        (b"D,,1", RejectReason.SYNTAX, ERROR_PROTOCOL),
        (b"D1,1", RejectReason.SYNTAX, ERROR_PROTOCOL),
        (b"D,1,\xff", RejectReason.SYNTAX, ERROR_PROTOCOL),
        (b"D,128,0", RejectReason.OUT_OF_RANGE, ERROR_OUT_OF_RANGE),
        (b"G,2147483648,0", RejectReason.OUT_OF_RANGE, ERROR_OUT_OF_RANGE),
        (b"L,2,1", RejectReason.OUT_OF_RANGE, ERROR_OUT_OF_RANGE),
        (b"L,0,3", RejectReason.OUT_OF_RANGE, ERROR_OUT_OF_RANGE),
    ],
)
def test_bad_commands_are_rejected_with_documented_error(
    line: bytes, reason: RejectReason, text: str
) -> None:
    result = parse_command(line)
    assert isinstance(result, Reject)
    assert result.reason is reason
    assert format_reply(error_reply(result)) == f"z,{text}\r\n".encode()


def test_limits_come_from_the_caller() -> None:
    specs = command_specs(KteamLimits(max_speed=20, leds=4, sensors=8))
    assert isinstance(parse_command(b"D,21,0", specs), Reject)
    assert parse_command(b"L,3,1", specs) == KteamCommand("L", (3, 1))
    assert isinstance(parse_reply(b"n," + b",".join([b"1"] * 8), specs), KteamReply)


def test_reply_round_trip_from_the_controller_side() -> None:
    replies = [
        KteamReply("b", ("koala-bridge 0.1",)),
        KteamReply("d"),
        KteamReply("e", ("12", "-12")),
        KteamReply("h", ("22222", "-5")),
        KteamReply("n", tuple(str(i * 60) for i in range(16))),
        KteamReply("z", (ERROR_PROTOCOL,)),
    ]
    for reply in replies:
        wire = format_reply(reply)
        assert wire.endswith(b"\r\n")
        assert parse_reply(wire.rstrip(b"\r\n")) == reply
    assert parse_reply(b"h,1,2").ints == (1, 2)  # type: ignore[union-attr]
    assert parse_reply(b"z,Protocol error").is_error  # type: ignore[union-attr]


@pytest.mark.parametrize("line", [b"h,1", b"h,1,x", b"H,1,2", b"e1,2", b"\xff", b"", b"n,1,2"])
def test_bad_replies_are_rejected(line: bytes) -> None:
    assert isinstance(parse_reply(line), Reject)


def test_format_command_and_its_guards() -> None:
    assert format_command(KteamCommand("D", (5, -5))) == b"D,5,-5\r"
    assert format_command(KteamCommand("H"), b"\r\n") == b"H\r\n"
    with pytest.raises(FrameError):
        format_command(KteamCommand("d"))
    with pytest.raises(FrameError):
        format_reply(KteamReply("b", ("a,b",)))


def test_line_splitter_accepts_cr_lf_crlf_across_chunks() -> None:
    splitter = LineSplitter()
    stream = b"B\rD,1,2\nE\r\nH\r"
    for cut in range(len(stream) + 1):
        splitter.reset()
        lines = splitter.feed(stream[:cut]) + splitter.feed(stream[cut:])
        assert lines == [b"B", b"D,1,2", b"E", b"H"], cut


def test_line_splitter_bounds_memory_and_recovers() -> None:
    splitter = LineSplitter(max_line=16)
    out = splitter.feed(b"x" * 10)
    out += splitter.feed(b"y" * 10_000)  # never terminated for a long time
    assert len(splitter._buf) == 0  # discarding, not buffering
    out += splitter.feed(b"zz\rH\r")
    assert [type(o) for o in out] == [Reject, bytes]
    assert isinstance(out[0], Reject) and out[0].reason is RejectReason.LINE_TOO_LONG
    assert out[1] == b"H"


def test_random_bytes_never_raise() -> None:
    rng = random.Random(1234)
    splitter = LineSplitter(max_line=64)
    for _ in range(200):
        chunk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 80)))
        for item in splitter.feed(chunk):
            if isinstance(item, bytes):
                result = parse_command(item)
                if isinstance(result, Reject):
                    assert error_reply(result).letter == "z"
                parse_reply(item)


# --------------------------------------------------------------------------- on a pty


class _Robot:
    """The robot side as the bridge will run it: transport -> splitter -> codec -> reply."""

    def __init__(self, port: PtyTransport) -> None:
        self.port = port
        self.lines = LineSplitter()
        self.encoders = (0, 0)
        self.speeds = (0, 0)
        self.rejected = 0

    def serve(self, timeout: float = 5.0) -> None:
        """Answer the complete lines waiting; waits until at least one line is complete."""
        items: list[bytes | Reject] = []
        while not items:
            assert self.port.wait(timeout), "client sent no complete line"
            items = self.lines.feed(self.port.read())
        for item in items:
            command = item if isinstance(item, Reject) else parse_command(item)
            if isinstance(command, Reject):
                self.rejected += 1
                reply = error_reply(command)
            elif command.letter == "D":
                self.speeds = (command.args[0], command.args[1])
                reply = KteamReply("d")
            elif command.letter == "E":
                reply = KteamReply("e", tuple(map(str, self.speeds)))
            elif command.letter == "G":
                self.encoders = (command.args[0], command.args[1])
                reply = KteamReply("g")
            elif command.letter == "H":
                reply = KteamReply("h", tuple(map(str, self.encoders)))
            else:
                reply = KteamReply(command.letter.lower())
            self.port.write(format_reply(reply))


@pytest.fixture
def robot() -> Iterator[_Robot]:
    with PtyTransport() as port:
        yield _Robot(port)


def _ask(client: serial.Serial, robot: _Robot, line: bytes) -> bytes:
    client.write(line)
    robot.serve()
    reply = client.read_until(b"\r\n")
    assert reply.endswith(b"\r\n"), reply
    return reply


def test_pyserial_client_talks_to_the_pty(robot: _Robot) -> None:
    with serial.Serial(robot.port.endpoint.path, 115200, timeout=5) as client:
        assert _ask(client, robot, b"D,10,-10\r") == b"d\r\n"
        assert _ask(client, robot, b"E\n") == b"e,10,-10\r\n"
        assert _ask(client, robot, b"G,100,-100\r\n") == b"g\r\n"
        assert parse_reply(_ask(client, robot, b"H\r").rstrip()) == KteamReply("h", ("100", "-100"))


def test_pty_keeps_serving_after_bad_input(robot: _Robot) -> None:
    rng = random.Random(7)
    with serial.Serial(robot.port.endpoint.path, 115200, timeout=5) as client:
        assert _ask(client, robot, b"X\r") == b"z,Unknown command\r\n"
        assert _ask(client, robot, b"D,1\r") == b"z,Protocol error\r\n"
        assert _ask(client, robot, b"D,500,0\r") == b"z,Out of range\r\n"
        garbage = (
            bytes(rng.randrange(256) for _ in range(300)).replace(b"\r", b"").replace(b"\n", b"")
        )
        client.write(garbage + b"\r")
        robot.serve()
        assert client.read_until(b"\r\n").startswith(b"z,")  # one error for the one bad line
        assert _ask(client, robot, b"D,3,4\r") == b"d\r\n"
        assert robot.speeds == (3, 4)
    assert robot.rejected == 4


def test_symlink_is_stable_and_removed(tmp_path: Path) -> None:
    link = tmp_path / "koala-kteam"
    with PtyTransport(link) as port:
        assert port.endpoint.path == str(link)
        with serial.Serial(str(link), timeout=5) as client:
            client.write(b"B\r")
            assert port.wait(5)
            assert port.read() == b"B\r"
    assert not link.exists()
