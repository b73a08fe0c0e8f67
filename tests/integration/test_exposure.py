"""Exposure (issue 12, item 5): nothing listens beyond loopback unless the user opts in, Zenoh
takes its own TLS configuration, the compass link can be signed (MAVLink 2), and two bridges
cannot send MAVLink to one ground-station port.

No test here sends a packet off loopback: a non-loopback address is either only decided about
(:meth:`BridgeSettings.exposure`) or one this host does not have (192.0.2.1, TEST-NET-1), which
the kernel refuses to bind before anything is sent.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import DEFAULT_CONFIG, free_port
from koala_bridge.cli.main import main
from koala_bridge.drivers.mavlink_codec import CompassDecoder, signing_timestamp
from koala_bridge.drivers.messages import TransportError
from koala_bridge.drivers.transports import open_byte_transport
from koala_bridge.runtime.buses import BusOpenError, open_buses
from koala_bridge.runtime.settings import (
    BridgeSettings,
    ConfigError,
    apply_override,
    is_loopback_host,
    load_config,
    locator_host,
    parse_override,
)
from koala_bridge.runtime.sim_source import SimulatedRobotSource
from koala_bridge.runtime.zenoh_io import ZenohLink, session_config
from pymavlink.dialects.v20 import common as mavlink2

#: An address of TEST-NET-1 (RFC 5737): never assigned to this host, so binding it fails locally.
UNASSIGNED = "192.0.2.1"


def config_with(*overrides: str) -> dict[str, Any]:
    config = load_config(DEFAULT_CONFIG)
    for text in overrides:
        config = apply_override(config, *parse_override(text))
    return config


def local_ports() -> list[str]:
    """Overrides keeping a run on free loopback ports (a bridge may be running)."""
    return [
        f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
        f"buses.mavlink.port={free_port('udp')}",
        "buses.can.socketcand_port=0",
        f'buses.can.virtual_channel="exposure-{free_port()}"',
    ]


def run_cli(capsys: pytest.CaptureFixture[str], *sets: str) -> tuple[int, list[str]]:
    args = ["run", "--clock", "fast", "--duration", "0.1", "--log-level", "ERROR"]
    for s in [*local_ports(), *sets]:
        args += ["--set", s]
    code = main(args)
    return code, capsys.readouterr().err.strip().splitlines()


# ------------------------------------------------------------------------- what listens where

@pytest.mark.parametrize(("host", "loopback"), [
    ("127.0.0.1", True), ("127.0.0.53", True), ("::1", True), ("[::1]", True),
    ("localhost", True), ("0.0.0.0", False), ("", False), ("::", False),
    ("192.168.1.5", False), ("10.0.0.1", False), ("koala.lan", False),
])
def test_loopback_decision(host: str, loopback: bool) -> None:
    assert is_loopback_host(host) is loopback


def test_locator_host() -> None:
    assert locator_host("tcp/127.0.0.1:7447") == "127.0.0.1"
    assert locator_host("tls/[::1]:7447") == "::1"
    assert locator_host("udp/0.0.0.0:7447#iface=eth0") == "0.0.0.0"
    assert locator_host("unixsock-stream//tmp/koala.sock") is None


NON_LOOPBACK = {
    "socketcand on every interface": ['buses.can.socketcand_host="0.0.0.0"'],
    "socketcand on a LAN address": ['buses.can.socketcand_host="192.168.1.5"'],
    "zenoh on every interface": ['zenoh.listen=["tcp/0.0.0.0:7447"]'],
    "zenoh on a LAN address": ['zenoh.listen=["tcp/127.0.0.1:7447", "tcp/192.168.1.5:7447"]'],
    "zenoh udp on [::]": ['zenoh.listen=["udp/[::]:7447"]'],
    "mavlink udp to a LAN host": ['buses.mavlink.host="192.168.1.5"'],
    "mavlink tcp on every interface": ['buses.mavlink.transport="tcp"',
                                       'buses.mavlink.host="0.0.0.0"'],
}


def test_the_shipped_configuration_exposes_nothing() -> None:
    assert BridgeSettings.from_config(config_with()).exposure() == []


@pytest.mark.parametrize("sets", NON_LOOPBACK.values(), ids=NON_LOOPBACK.keys())
def test_non_loopback_is_refused_unless_opted_in(sets: list[str]) -> None:
    with pytest.raises(ConfigError, match=r"allow_non_loopback = true") as e:
        BridgeSettings.from_config(config_with(*sets))
    assert "\n" not in str(e.value)
    settings = BridgeSettings.from_config(config_with(*sets, "run.allow_non_loopback=true"))
    exposed = settings.exposure()
    assert len(exposed) == 1, exposed
    assert any(h in exposed[0] for h in ("0.0.0.0", "192.168.1.5", "::")), exposed


def test_connecting_out_is_not_listening() -> None:
    """A client of a router elsewhere (docs/multihost.md) opens no port: no opt-in needed."""
    settings = BridgeSettings.from_config(config_with(
        'zenoh.mode="client"', 'zenoh.connect=["tcp/192.168.1.5:7447"]', "zenoh.listen=[]"))
    assert settings.exposure() == []


@pytest.mark.parametrize("sets", [NON_LOOPBACK["socketcand on every interface"],
                                  NON_LOOPBACK["zenoh on every interface"]])
def test_run_refuses_with_one_line(capsys: pytest.CaptureFixture[str], sets: list[str]) -> None:
    code, lines = run_cli(capsys, *sets)
    assert code == 2 and len(lines) == 1, lines
    assert "reachable from the network" in lines[0] and "allow_non_loopback" in lines[0]


def test_opted_in_run_warns_what_listens_where(capsys: pytest.CaptureFixture[str],
                                               caplog: pytest.LogCaptureFixture) -> None:
    # An address this host does not have: the config is accepted and the warning logged, then
    # the kernel refuses the bind (nothing is ever served or sent off loopback).
    caplog.set_level(logging.WARNING)
    code, lines = run_cli(capsys, "run.allow_non_loopback=true",
                          f'buses.can.socketcand_host="{UNASSIGNED}"')
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(f"socketcand listens on {UNASSIGNED}:0" in w and "reachable from the network" in w
               for w in warnings), warnings
    assert code == 1 and len(lines) == 1 and "cannot open bus can.socketcand" in lines[0], lines


def test_opted_in_zenoh_listen_warns(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    settings = BridgeSettings.from_config(config_with(
        "run.allow_non_loopback=true", f'zenoh.listen=["tcp/{UNASSIGNED}:{free_port()}"]'))
    with pytest.raises(OSError, match="cannot open the Zenoh session"):
        ZenohLink(settings.zenoh, dict)
    assert any(f"Zenoh listens on tcp/{UNASSIGNED}" in r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------------- Zenoh TLS

@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A CA and a server certificate for localhost / 127.0.0.1, made with the openssl CLI."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed")
    d = tmp_path_factory.mktemp("tls")

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True, timeout=60)

    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
        "-days", "2", "-subj", "/CN=koala-test-ca")
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
        "-subj", "/CN=localhost")
    (d / "ext.cnf").write_text(
        "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\n")
    ssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
        "-CAcreateserial", "-out", "server.pem", "-days", "2", "-extfile", "ext.cnf")
    return {"ca": d / "ca.pem", "key": d / "server.key", "cert": d / "server.pem", "dir": d}


def zenoh_client(endpoint: str, tls: dict[str, Any] | None = None) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    if tls is not None:
        c.insert_json5("transport/link/tls", json.dumps(tls))
    return zenoh.open(c)


@pytest.fixture
def tls_link(certificates: dict[str, Path], tmp_path: Path) -> Iterator[tuple[ZenohLink, int]]:
    port = free_port()
    zenoh_file = tmp_path / "zenoh.json5"
    # Zenoh's own format; its mode and listen endpoints are overridden by [zenoh] (ours win).
    zenoh_file.write_text(
        "{\n  // TLS for the bridge's listener\n"
        '  mode: "router",\n  listen: { endpoints: ["tcp/127.0.0.1:1"] },\n'
        "  transport: { link: { tls: {\n"
        f'    listen_private_key: "{certificates["key"]}",\n'
        f'    listen_certificate: "{certificates["cert"]}",\n'
        "  } } },\n}\n"
    )
    settings = BridgeSettings.from_config(config_with(
        f'zenoh.listen=["tls/127.0.0.1:{port}"]', f'zenoh.config_file="{zenoh_file}"',
        'zenoh.prefix="tls/koala"'))
    config = session_config(settings.zenoh)
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("listen/endpoints")) == [f"tls/127.0.0.1:{port}"]
    assert json.loads(config.get_json("transport/link/tls/listen_certificate")) == str(
        certificates["cert"])
    link = ZenohLink(settings.zenoh, lambda: {"world": 1})
    try:
        yield link, port
    finally:
        link.close()


def test_zenoh_tls_session_on_loopback(tls_link: tuple[ZenohLink, int],
                                       certificates: dict[str, Path]) -> None:
    link, port = tls_link
    got = threading.Event()
    payloads: list[bytes] = []

    def on_sample(sample: zenoh.Sample) -> None:
        payloads.append(sample.payload.to_bytes())
        got.set()

    client = zenoh_client(f"tls/localhost:{port}",
                          {"root_ca_certificate": str(certificates["ca"])})
    try:
        sub = client.declare_subscriber("tls/koala/probe", on_sample)
        deadline = time.monotonic() + 20
        while not got.is_set() and time.monotonic() < deadline:
            link.publish("probe", {"t": 1.0})
            got.wait(0.2)
        sub.undeclare()
        assert payloads and json.loads(payloads[0]) == {"t": 1.0}
        replies = list(client.get("tls/koala/world", timeout=10))
        assert replies and json.loads(replies[0].ok.payload.to_bytes()) == {"world": 1}
    finally:
        client.close()


def test_zenoh_tls_refuses_a_client_without_the_ca(tls_link: tuple[ZenohLink, int]) -> None:
    _, port = tls_link
    with pytest.raises(zenoh.ZError):  # a client cannot open without its one router
        zenoh_client(f"tls/localhost:{port}").close()
    with pytest.raises(zenoh.ZError):  # nor in plain TCP on the TLS port
        zenoh_client(f"tcp/127.0.0.1:{port}").close()


def test_zenoh_config_file_errors_are_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "zenoh.json5"
    bad.write_text("{ mode: ")
    for path in (bad, tmp_path / "missing.json5"):
        settings = BridgeSettings.from_config(config_with(f'zenoh.config_file="{path}"'))
        with pytest.raises(ConfigError, match=r"^\[zenoh\] 'config_file'") as e:
            session_config(settings.zenoh)
        assert "\n" not in str(e.value)


# ------------------------------------------------------------------------- MAVLink signing

KEY = bytes(range(32))


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    f = tmp_path / "mavlink.key"
    f.write_text(KEY.hex() + "\n")
    return f


@pytest.mark.parametrize(("content", "message"), [
    (None, "cannot read it"), ("", "64 hex digits"), ("abc", "64 hex digits"),
    ("zz" * 32, "64 hex digits"), (KEY.hex() + "00", "64 hex digits"),
])
def test_a_bad_key_file_is_a_config_error(tmp_path: Path, content: str | None,
                                          message: str) -> None:
    f = tmp_path / "mavlink.key"
    if content is not None:
        f.write_text(content)
    settings = BridgeSettings.from_config(config_with(f'buses.mavlink.signing_key_file="{f}"'))
    with pytest.raises(ConfigError, match=message) as e:
        settings.buses.mavlink.signing(time.time())
    assert "signing_key_file" in str(e.value) and "\n" not in str(e.value)
    if content:
        assert content not in str(e.value)  # a secret is never echoed


def test_run_with_a_missing_key_file_is_one_line(capsys: pytest.CaptureFixture[str],
                                                 tmp_path: Path) -> None:
    code, lines = run_cli(capsys, f'buses.mavlink.signing_key_file="{tmp_path / "none.key"}"')
    assert code == 2 and len(lines) == 1, lines
    assert "'signing_key_file'" in lines[0] and "cannot read it" in lines[0]


def gcs_parser(key: bytes | None) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, 255, 190)
    mav.robust_parsing = True
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = signing_timestamp(time.time())
    return mav


def test_signed_compass_link(key_file: Path) -> None:
    """The bridge signs; a ground station with the key verifies; one with another key rejects
    every packet; the bridge accepts the holder's signed packets and rejects unsigned ones."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(10)
        config = config_with(*local_ports(), "run.clock=fast",
                             f"buses.mavlink.port={gcs.getsockname()[1]}",
                             f'buses.mavlink.signing_key_file="{key_file}"',
                             "buses.mavlink.signing_link_id=7")
        service = SimulatedRobotSource(config, BridgeSettings.from_config(config))
        stop = threading.Event()
        with service:
            service.open()
            runner = threading.Thread(target=service.run, args=(stop,), kwargs={"duration_s": 0})
            runner.start()
            try:
                holder, stranger, unkeyed = gcs_parser(KEY), gcs_parser(os.urandom(32)), \
                    gcs_parser(None)
                kinds: dict[str, set[str]] = {"holder": set(), "stranger": set(), "none": set()}
                while not {"SCALED_IMU", "HEARTBEAT"} <= kinds["holder"]:
                    data, bridge_addr = gcs.recvfrom(4096)
                    assert data[2] & mavlink2.MAVLINK_IFLAG_SIGNED and data[-13] == 7
                    for name, mav in (("holder", holder), ("stranger", stranger),
                                      ("none", unkeyed)):
                        kinds[name] |= {m.get_type() for m in mav.parse_buffer(data) or []}
                assert holder.signing.goodsig_count > 0 and holder.signing.badsig_count == 0
                assert kinds["stranger"] == {"BAD_DATA"}
                # pymavlink without a key does not check signatures (module docstring)
                assert "SCALED_IMU" in kinds["none"]

                def counts() -> dict[str, int]:
                    return service.status(0.0)["buses"]["mavlink"]

                before = counts()
                gcs.sendto(unkeyed.heartbeat_encode(6, 8, 0, 0, 4).pack(unkeyed), bridge_addr)
                gcs.sendto(stranger.heartbeat_encode(6, 8, 0, 0, 4).pack(stranger), bridge_addr)
                assert wait_for(lambda: counts()["rejected"] == before["rejected"] + 2)
                gcs.sendto(holder.heartbeat_encode(6, 8, 0, 0, 4).pack(holder), bridge_addr)
                assert wait_for(lambda: counts()["received"] == before["received"] + 1)
                assert counts()["rejected"] == before["rejected"] + 2
            finally:
                stop.set()
                runner.join(30)


def wait_for(predicate: Any, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return bool(predicate())


def test_decoder_accept_unsigned_still_rejects_bad_signatures() -> None:
    from koala_bridge.drivers.mavlink_codec import MavlinkSigning

    dec = CompassDecoder(signing=MavlinkSigning(KEY, accept_unsigned=True))
    plain, stranger = gcs_parser(None), gcs_parser(os.urandom(32))
    assert dec.feed_datagram(plain.heartbeat_encode(6, 8, 0, 0, 4).pack(plain))
    assert dec.feed_datagram(stranger.heartbeat_encode(6, 8, 0, 0, 4).pack(stranger)) == []
    assert dec.rejected == 1 and dec.last_reject is not None
    assert "Invalid signature" in dec.last_reject.detail


def test_decoder_rejects_replays_and_is_not_blocked_by_forged_timestamps() -> None:
    from koala_bridge.drivers.mavlink_codec import MavlinkSigning

    dec = CompassDecoder(signing=MavlinkSigning(KEY, initial_timestamp=signing_timestamp(
        time.time())))
    holder, forger = gcs_parser(KEY), gcs_parser(os.urandom(32))
    forger.signing.timestamp += 10**12  # far in the future, under the wrong key
    assert dec.feed_datagram(forger.heartbeat_encode(6, 8, 0, 0, 4).pack(forger)) == []
    genuine = holder.heartbeat_encode(6, 8, 0, 0, 4).pack(holder)
    assert len(dec.feed_datagram(genuine)) == 1  # pymavlink alone would call it "old"
    assert dec.feed_datagram(genuine) == []      # the same packet again: a replay
    assert dec.rejected == 2 and dec.decoded == 1


# ------------------------------------------------------------------------- one sender per port

def test_two_bridges_on_one_mavlink_udp_port_are_refused(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    port = free_port("udp")
    only_mavlink = [
        "buses.kteam.enabled=false", "buses.rangefinders.enabled=false",
        "buses.can.socketcand=false", "buses.can.slcan=false", "buses.can.virtual=false",
        f"buses.mavlink.port={port}",
    ]
    first = open_buses(BridgeSettings.from_config(config_with(*only_mavlink)).buses)
    try:
        with pytest.raises(BusOpenError, match=f"already sends to 127.0.0.1:{port}"):
            open_buses(BridgeSettings.from_config(config_with(*only_mavlink)).buses)
        # the same through the CLI: one line, exit 1 (the machine refused), as a port in use
        code, lines = run_cli(capsys, *only_mavlink)
        assert code == 1 and len(lines) == 1, lines
        assert "cannot open bus mavlink" in lines[0] and f"127.0.0.1:{port}" in lines[0]
    finally:
        first.close()
    # the claim goes with the first bridge
    open_buses(BridgeSettings.from_config(config_with(*only_mavlink)).buses).close()


def test_exclusive_udp_claim_names_the_resolved_destination() -> None:
    port = free_port("udp")
    with open_byte_transport(f"udp://127.0.0.1:{port}?exclusive=1"):
        with pytest.raises(TransportError, match="already sends to"):
            open_byte_transport(f"udp://localhost:{port}?exclusive=1")
        # without the option (a test's or a tool's sender) nothing is claimed
        open_byte_transport(f"udp://127.0.0.1:{port}").close()
