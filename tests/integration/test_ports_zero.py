"""Every port the bridge opens takes 0 ("any free port"), and the endpoints file names the port
actually bound (issue 17, point 5): two bridges on one host never race for a port.

Real transports on loopback: a Zenoh client connects to the locator the endpoints name and asks
for the world; a MAVLink client on ``udpout:`` (pymavlink's MAVLink 2 parser) sends a HEARTBEAT
and receives the compass; python-can's socketcand interface opens the named port.
"""

from __future__ import annotations

import json
import math
import re
import socket
import time
from pathlib import Path

import pytest
import zenoh
from _inproc import bridge, socketcand
from koala_bridge.runtime.endpoints import write_endpoints_file
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

pytestmark = pytest.mark.integration

ZERO = ("buses.can.socketcand_port=0", "buses.mavlink.port=0",
        'zenoh.listen=["tcp/127.0.0.1:0"]', 'run.clock="fast"')


def test_two_bridges_on_port_zero_report_distinct_bound_ports(tmp_path) -> None:
    with bridge(*ZERO) as a, bridge(*ZERO) as b:
        files = [write_endpoints_file(tmp_path / f"{n}.json", s.endpoints)  # type: ignore[arg-type]
                 for n, s in (("a", a), ("b", b))]
        eps = [json.loads(f.read_text()) for f in files]
        ports = set()
        for ep in eps:
            (locator,) = ep["zenoh"]["endpoints"]
            assert re.fullmatch(r"tcp/127\.0\.0\.1:\d+", locator), locator
            assert not locator.endswith(":0")
            kind, host, port = ep["mavlink"]["url"].split(":")
            assert (kind, host) == ("udpout", "127.0.0.1") and int(port) > 0
            assert ep["can"]["socketcand"]["port"] > 0
            ports |= {int(locator.rsplit(":", 1)[1]), int(port), ep["can"]["socketcand"]["port"]}
        assert len(ports) == 6  # all six bound, none shared

        # Zenoh: the world queryable answers on the locator the file names
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps(eps[1]["zenoh"]["endpoints"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(conf)
        try:
            replies = [r.ok for r in session.get(f"{eps[1]['zenoh']['prefix']}/world",
                                                  timeout=10) if r.ok is not None]
        finally:
            session.close()
        assert replies and "segments" in json.loads(bytes(replies[0].payload.to_bytes()))

        # MAVLink: the client sends first, then receives the compass on its socket
        _, host, port = eps[0]["mavlink"]["url"].split(":")
        parser = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as mav:
            mav.connect((host, int(port)))
            mav.settimeout(0.5)
            heartbeat = parser.heartbeat_encode(mavlink2.MAV_TYPE_GCS,
                                                mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            got: set[str] = set()
            deadline = time.monotonic() + 15
            while "SCALED_IMU" not in got and time.monotonic() < deadline:
                mav.send(heartbeat.pack(parser))
                try:
                    data = mav.recv(65536)
                except TimeoutError:
                    continue
                got |= {m.get_type() for m in parser.parse_buffer(data) or []}
        assert "SCALED_IMU" in got, got

        # socketcand: python-can opens the port the endpoints name
        bus = socketcand(a)
        try:
            assert bus.recv(timeout=10) is not None
        finally:
            bus.shutdown()


README = Path(__file__).resolve().parents[2] / "README.md"


def readme_mavlink_snippet() -> str:
    """The README's MAVLink client lines, from its "# MAVLink compass" comment to the blank
    line after them."""
    text = README.read_text()
    start = text.index("# MAVLink compass")
    return text[start:text.index("\n\n", start)]


@pytest.mark.parametrize("overrides", [ZERO, ('run.clock="fast"',)],
                         ids=["udpout-port-0", "udpin-fixed-port"])
def test_the_readme_mavlink_snippet_hears_the_compass_on_either_kind_of_url(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, overrides: tuple[str, ...]) -> None:
    """Port 0 makes the url udpout: and the client must send first; the README's snippet sends
    a HEARTBEAT, which pymavlink drops on udpin: -- the same lines work with both."""
    monkeypatch.setenv("MAVLINK20", "1")  # as the snippet says; the dialect chosen again
    monkeypatch.setattr(mavutil, "mavlink", mavutil.mavlink)
    mavutil.set_dialect(mavutil.current_dialect)
    snippet = readme_mavlink_snippet()
    assert "heartbeat_send" in snippet
    with bridge(*overrides) as source:
        ep = json.loads(write_endpoints_file(tmp_path / "ep.json",
                                             source.endpoints).read_text())  # type: ignore[arg-type]
        assert ep["mavlink"]["url"].startswith("udpout:" if overrides == ZERO else "udpin:")
        printed: list[object] = []
        scope = {"ep": ep, "mavutil": mavutil, "math": math, "print": printed.append}
        try:
            exec(snippet, scope)  # noqa: S102 - the README's own lines
        finally:
            if "gcs" in scope:
                scope["gcs"].close()  # type: ignore[attr-defined]
    assert scope["imu"] is not None, "no SCALED_IMU within the snippet's 5 s"
    (heading,) = printed
    assert 0 <= float(heading) < 360  # type: ignore[arg-type]
