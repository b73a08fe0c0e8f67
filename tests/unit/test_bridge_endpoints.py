"""bridge.endpoints and bridge.counters: the endpoints file's exact shape, atomic writing."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import pytest
from koala_bridge.runtime.counters import BusCounters
from koala_bridge.runtime.endpoints import Endpoints, SocketcandEndpoint, write_endpoints_file


def sample() -> Endpoints:
    return Endpoints(
        kteam="/dev/pts/7",
        rangefinders="/dev/pts/8",
        socketcand=SocketcandEndpoint("127.0.0.1", 29536, "koala0"),
        slcan="/dev/pts/9",
        dbc="/abs/config/koala.dbc",
        mavlink_url="udpin:127.0.0.1:14550",
        zenoh_endpoints=("tcp/127.0.0.1:7447",),
        zenoh_prefix="koala/koala",
        virtual_can_channel="koala",
    )


def test_endpoints_json_has_exactly_the_issue_shape() -> None:
    assert sample().to_json_dict() == {
        "serial": {"kteam": "/dev/pts/7", "rangefinders": "/dev/pts/8"},
        "can": {
            "socketcand": {"host": "127.0.0.1", "port": 29536, "channel": "koala0"},
            "slcan": "/dev/pts/9",
            "dbc": "/abs/config/koala.dbc",
        },
        "mavlink": {"url": "udpin:127.0.0.1:14550"},
        "zenoh": {"endpoints": ["tcp/127.0.0.1:7447"], "prefix": "koala/koala"},
    }


def test_disabled_buses_are_null() -> None:
    d = Endpoints(zenoh_endpoints=("tcp/127.0.0.1:1",), zenoh_prefix="k").to_json_dict()
    assert d["serial"] == {"kteam": None, "rangefinders": None}
    assert d["can"]["socketcand"] is None
    assert d["mavlink"]["url"] is None


def test_write_is_atomic_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "endpoints.json"
    write_endpoints_file(target, sample())
    assert json.loads(target.read_text()) == sample().to_json_dict()
    assert os.listdir(target.parent) == ["endpoints.json"]


def test_write_failure_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "endpoints.json"
    target.mkdir()  # os.replace onto a directory fails
    with pytest.raises(OSError):
        write_endpoints_file(target, sample())
    assert sorted(os.listdir(tmp_path)) == ["endpoints.json"]


def test_describe_names_every_endpoint() -> None:
    text = sample().describe()
    for needle in ("/dev/pts/7", "/dev/pts/8", "127.0.0.1:29536 channel koala0", "/dev/pts/9",
                   "udpin:127.0.0.1:14550", "tcp/127.0.0.1:7447", "prefix koala/koala"):
        assert needle in text
    # The prefix reads as in the endpoints file: no trailing "/" (keys are PREFIX + "/" + key).
    assert "koala/koala/" not in text
    assert sample().to_json_dict()["zenoh"]["prefix"] == "koala/koala"


def test_describe_says_a_udpout_mavlink_client_sends_first() -> None:
    """With port 0 the bridge listens on a port it picked and streams to whoever wrote to it:
    the banner says so, or a client that only listens hears nothing."""
    out = Endpoints(mavlink_url="udpout:127.0.0.1:40123").describe()
    (line,) = [x for x in out.splitlines() if "MAVLink" in x]
    assert "mavutil.mavlink_connection('udpout:127.0.0.1:40123')" in line
    assert "send first (a HEARTBEAT)" in line
    assert "send first" not in sample().describe()  # udpin: the bridge sends to the client


def test_counters_are_thread_safe_and_snapshot_sorted() -> None:
    counters = BusCounters(["kteam"])

    def hammer() -> None:
        for _ in range(10_000):
            counters.received("kteam")
            counters.rejected("can.slcan")

    threads = [threading.Thread(target=hammer) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    snap = counters.snapshot()
    assert list(snap) == ["can.slcan", "kteam"]
    assert snap["kteam"] == {"sent": 0, "received": 40_000, "rejected": 0}
    assert snap["can.slcan"]["rejected"] == 40_000
    with pytest.raises(ValueError):
        counters.add("kteam", "lost")
