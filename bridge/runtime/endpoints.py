"""Where each client connects: the endpoints file (for programs) and the start banner (for people).

The endpoints file is JSON with exactly this shape (issue 2, item 8)::

    {"serial": {"kteam": PATH, "rangefinders": PATH},
     "can": {"socketcand": {"host": H, "port": P, "channel": C}, "slcan": PATH, "dbc": ABS_PATH},
     "mavlink": {"url": PYMAVLINK_CONNECTION_STRING},
     "zenoh": {"endpoints": [...], "prefix": PREFIX},
     "foxglove": {"url": "ws://HOST:PORT"}}          (only with run --foxglove)

A bus that is disabled in the configuration appears as ``null``.

With several robots (``[[robots]]``, docs/multirobot.md) the file holds one such object per
robot, under its name, in the configuration's order::

    {"robots": {"alpha": {"serial": ..., "can": ..., "mavlink": ..., "zenoh": ...},
                "beta": {...}},
     "foxglove": {"url": "ws://HOST:PORT"}}          (only with run --foxglove: one server)
 The file is written atomically
(a temporary file in the same directory, then ``os.replace``), so a reader never sees half a file,
and only after every endpoint accepts clients.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from koala_bridge.drivers.dialects import dialect

if TYPE_CHECKING:
    from koala_bridge.runtime.buses import OpenBuses
    from koala_bridge.runtime.settings import BridgeSettings


@dataclass(frozen=True)
class SocketcandEndpoint:
    host: str
    port: int
    channel: str


@dataclass(frozen=True)
class Endpoints:
    """Every place a client can connect to, as the bridge opened them."""

    kteam: str | None = None
    kteam_dialect: str = "koala1"               # banner only: [buses.kteam] dialect
    rangefinders: str | None = None
    socketcand: SocketcandEndpoint | None = None
    slcan: str | None = None
    dbc: str | None = None
    mavlink_url: str | None = None
    zenoh_endpoints: tuple[str, ...] = ()
    zenoh_prefix: str = ""
    virtual_can_channel: str | None = None      # in-process only: not in the file
    foxglove_url: str | None = None             # run --foxglove: in the file only then
    extra: dict[str, str] = field(default_factory=dict)

    def to_json_dict(self) -> dict[str, Any]:
        """The endpoints file's content (see the module docstring)."""
        sc = self.socketcand
        return {
            "serial": {"kteam": self.kteam, "rangefinders": self.rangefinders},
            "can": {
                "socketcand": (
                    {"host": sc.host, "port": sc.port, "channel": sc.channel} if sc else None
                ),
                "slcan": self.slcan,
                "dbc": self.dbc,
            },
            "mavlink": {"url": self.mavlink_url},
            "zenoh": {"endpoints": list(self.zenoh_endpoints), "prefix": self.zenoh_prefix},
            # the live view (run --foxglove, docs/foxglove.md); absent when it is off
            **({"foxglove": {"url": self.foxglove_url}} if self.foxglove_url else {}),
        }

    def describe(self) -> str:
        """A few lines telling a person where each client connects, with a one-line example."""
        off = "(disabled)"
        lines = ["koala-bridge is serving. Connect clients to:"]
        lines.append(
            f"  K-Team serial (ASCII)   {self.kteam or off}"
            + (f"   {self.kteam_dialect}: e.g. serial.Serial(PATH, "
               f"{_serial_args(self.kteam_dialect)})" if self.kteam else "")
        )
        lines.append(f"  Range frames (binary)   {self.rangefinders or off}")
        if self.socketcand:
            sc = self.socketcand
            lines.append(
                f"  CAN socketcand          {sc.host}:{sc.port} channel {sc.channel}"
                f"   e.g. can.Bus(interface='socketcand', host='{sc.host}', port={sc.port},"
                f" channel='{sc.channel}')"
            )
        else:
            lines.append(f"  CAN socketcand          {off}")
        lines.append(
            f"  CAN slcan               {self.slcan or off}"
            + (f"   e.g. can.Bus(interface='slcan', channel='{self.slcan}')" if self.slcan else "")
        )
        if self.virtual_can_channel:
            lines.append(
                f"  CAN virtual             channel '{self.virtual_can_channel}' (in-process only)"
            )
        lines.append(f"  CAN database (DBC)      {self.dbc or off}")
        mav = self.mavlink_url
        lines.append(
            f"  MAVLink                 {mav or off}"
            + (f"   e.g. mavutil.mavlink_connection('{mav}')" if mav else "")
            # udpout: the bridge listens on a port it picked and knows no client until one
            # writes: the client sends first (docs/protocols.md "Links and connection strings")
            + ("; send first (a HEARTBEAT): the bridge streams to whoever wrote to it"
               if mav and mav.startswith("udpout:") else "")
        )
        if self.zenoh_prefix:
            where = ", ".join(self.zenoh_endpoints) or "(no listen endpoint: see [zenoh] connect)"
            lines.append(f"  Zenoh                   {where}  prefix {self.zenoh_prefix}")
        else:
            lines.append(f"  Zenoh                   {off}")
        if self.foxglove_url:
            lines.append(f"  Foxglove (live view)    {self.foxglove_url}   open it in Foxglove: "
                         "Open connection > Foxglove WebSocket (docs/foxglove.md)")
        for name, where in sorted(self.extra.items()):
            lines.append(f"  {name:<23} {where}")
        return "\n".join(lines)


@dataclass(frozen=True)
class FleetEndpoints(Endpoints):
    """Where each robot of ``[[robots]]`` takes clients: ``robots`` (name, its endpoints) in
    the configuration's order (the fields of :class:`Endpoints` itself stay empty)."""

    robots: tuple[tuple[str, Endpoints], ...] = ()

    def to_json_dict(self) -> dict[str, Any]:
        """The endpoints file's content: ``{"robots": {name: one robot's object}}``, and
        ``"foxglove": {"url": ...}`` beside it with run --foxglove (one server for all)."""
        return {"robots": {name: ep.to_json_dict() for name, ep in self.robots},
                **({"foxglove": {"url": self.foxglove_url}} if self.foxglove_url else {})}

    def describe(self) -> str:
        """Each robot's lines of :meth:`Endpoints.describe`, under its name."""
        lines = [f"koala-bridge is serving {len(self.robots)} robots in one world."]
        for name, ep in self.robots:
            lines.append(f"Robot {name}:")
            lines += ["  " + line for line in ep.describe().splitlines()[1:]]
        if self.foxglove_url:
            lines.append(f"  Foxglove (live view)    {self.foxglove_url}   every robot; open it "
                         "in Foxglove: Open connection > Foxglove WebSocket (docs/foxglove.md)")
        return "\n".join(lines)

    def robot(self, name: str) -> Endpoints:
        """The endpoints of robot ``name``."""
        for n, ep in self.robots:
            if n == name:
                return ep
        raise KeyError(name)


def _serial_args(dialect_name: str) -> str:
    """pyserial arguments opening a port as the dialect's robot has it (a pty ignores them)."""
    line = dialect(dialect_name).line
    return (f"{line.baudrate}, bytesize={line.bytesize}, parity='{line.parity}', "
            f"stopbits={line.stopbits:g}")


def endpoints_of(buses: OpenBuses, settings: BridgeSettings, zenoh: bool = True,
                 zenoh_listening: Sequence[str] | None = None) -> Endpoints:
    """Where clients connect to ``buses`` opened from ``settings`` (``run`` and ``replay``).

    ``zenoh``: whether a Zenoh session listens on ``[zenoh] listen`` under ``[zenoh] prefix``;
    ``zenoh_listening``: the locators it actually bound (a port 0 resolved), if known.
    """
    socketcand = None
    if "can.socketcand" in buses.can:
        ep = buses.can["can.socketcand"].endpoint
        socketcand = SocketcandEndpoint(str(ep.host), int(ep.port or 0), str(ep.channel))
    mav_url = None
    if buses.mavlink is not None:
        ep = buses.mavlink.transport.endpoint
        mav_url = settings.buses.mavlink.client_url(pty_path=ep.path, bound_port=ep.port)
    return Endpoints(
        kteam=buses.kteam.transport.endpoint.path if buses.kteam else None,
        kteam_dialect=settings.buses.kteam_dialect,
        rangefinders=buses.rangefinders.transport.endpoint.path if buses.rangefinders else None,
        socketcand=socketcand,
        slcan=buses.can["can.slcan"].endpoint.path if "can.slcan" in buses.can else None,
        # [buses.can] dbc, the database clients decode the CAN bus with; no CAN bus, no DBC
        dbc=str(settings.buses.can.dbc_path.resolve()) if buses.can else None,
        mavlink_url=mav_url,
        zenoh_endpoints=(
            () if not zenoh
            else tuple(zenoh_listening) if zenoh_listening is not None
            else settings.zenoh.listen
        ),
        zenoh_prefix=settings.zenoh.prefix if zenoh else "",
        virtual_can_channel=(
            buses.can["can.virtual"].endpoint.channel if "can.virtual" in buses.can else None
        ),
    )


def write_endpoints_file(path: str | os.PathLike[str], endpoints: Endpoints) -> Path:
    """Write ``endpoints`` as JSON to ``path`` atomically (temporary file + rename)."""
    target = Path(path).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(endpoints.to_json_dict(), f, indent=2)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return target
