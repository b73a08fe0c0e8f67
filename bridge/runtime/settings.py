"""Configuration: read a TOML file, apply command-line overrides, type the bridge's sections.

Precedence is explicit: command line > file. Nothing is read from the environment or the home
directory, and every default a run uses is written in ``config/default.toml``. This module types
the sections the bridge owns — ``[run]``, ``[buses]`` and ``[zenoh]`` — and leaves ``[sim]``,
``[robot]``, ``[world]`` and the sensor sections to ``sim/`` (which validates them the same way).
Unknown keys are errors that name the section and suggest the nearest valid key.

Command-line overrides use dotted keys and TOML values, e.g.
``--set buses.mavlink.port=14551 --set 'zenoh.listen=["tcp/127.0.0.1:7500"]'``.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import ipaddress
import logging
import math
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from koala_bridge.core.resources import default_dbc_path
from koala_bridge.core.schema import (
    MAX_MAGNITUDE,
    Bool,
    ConfigError,
    NonNegative,
    Positive,
    PositiveInt,
    Str,
    field_names,
    one_of,
    reject_unknown,
    section,
    tuples,
    validate,
)
from koala_bridge.drivers.dialects import DIALECTS
from koala_bridge.runtime.clock import CLOCK_NAMES
from koala_bridge.runtime.wire import FRAMING_RULE, serial_bits_per_byte
from pydantic import AfterValidator, BeforeValidator, Field, Strict

if TYPE_CHECKING:
    from koala_bridge.drivers.can_codec import KoalaCanCodec
    from koala_bridge.drivers.kteam import SerialLine
    from koala_bridge.drivers.mavlink_codec import MavlinkSigning

log = logging.getLogger(__name__)

__all__ = [
    "BridgeSettings",
    "BusesSettings",
    "CanSettings",
    "ConfigError",
    "MavlinkSettings",
    "LockstepSettings",
    "RunSettings",
    "ZenohSettings",
    "apply_override",
    "is_loopback_host",
    "locator_host",
    "load_config",
    "parse_override",
]

MAVLINK_TRANSPORTS = ("udp", "tcp", "pty")
#: K-Team serial dialects (docs/protocols.md §1): ``koala1`` = classic Koala / Koala II (KoreBot
#: ``koala.c``), ``koala25`` = Koala 2.5 (``libkoala``, Koala 2.5 user manual §6).
KTEAM_DIALECTS = tuple(DIALECTS)

#: A Zenoh locator whose port is 0 (``tcp/127.0.0.1:0``, ``udp/[::1]:0#iface=lo``, ...).
ZERO_PORT = re.compile(r":0+(?:[?#].*)?$")

#: The top-level tables of a configuration: sim/ reads the first four (sim/config.py), the bridge
#: the others (``[real]``: runtime/real_source.py, for ``run --source real``; ``[localisation]``:
#: bridge/runtime/localisation.py, the estimator node).
SECTIONS = ("sim", "robot", "sensors", "world", "run", "buses", "zenoh", "real", "localisation",
            "lockstep", "faults", "robots")


#: The keys that name an input file. A relative path in a config file is relative to that file's
#: folder (so a copy made by ``koala-bridge config init`` finds the DBC beside it wherever it is
#: run from); given with ``--set``, relative to the working directory.
PATH_KEYS = (("buses", "can", "dbc"), ("buses", "mavlink", "signing_key_file"),
             ("zenoh", "config_file"))


def load_config(path: str | Path) -> dict[str, Any]:
    """Read the TOML file ``path``; errors name the file and, for syntax errors, the line.
    Relative file paths of :data:`PATH_KEYS` are made relative to the file's folder."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError as e:
        raise ConfigError(f"config file not found: {p}") from e
    except OSError as e:
        raise ConfigError(f"cannot read config file {p}: {e.strerror}") from e
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(
            f"{p}: {len(raw)} bytes is not a configuration (at most {MAX_CONFIG_BYTES} bytes)"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        # TOML is UTF-8 (toml.io); a UTF-16 file (a BOM FF FE / FE FF) is a common editor slip
        hint = " (it looks like UTF-16: save it as UTF-8)" if raw[:2] in (
            b"\xff\xfe", b"\xfe\xff") else ""
        raise ConfigError(
            f"{p}: not a UTF-8 text file (byte {e.start}: {raw[e.start]:#04x}){hint}"
        ) from None
    return _paths_beside(_parse_toml(text, str(p)), p.parent)


def map_relative_paths(config: dict[str, Any], change: Callable[[str], str]) -> dict[str, Any]:
    """``config`` (changed in place) with each relative path of :data:`PATH_KEYS` replaced by
    ``change(path)``."""
    for keys in PATH_KEYS:
        table: Any = config
        for k in keys[:-1]:
            table = table.get(k) if isinstance(table, dict) else None
        value = table.get(keys[-1]) if isinstance(table, dict) else None
        if isinstance(value, str) and value and not Path(value).expanduser().is_absolute():
            table[keys[-1]] = change(value)
    return config


def _paths_beside(config: dict[str, Any], folder: Path) -> dict[str, Any]:
    """``config`` with each relative path of :data:`PATH_KEYS` joined to ``folder``."""
    return map_relative_paths(config, lambda value: str(folder / value))


#: Larger than any configuration (default.toml is ~20 kB); a bigger file is the wrong file.
MAX_CONFIG_BYTES = 4 << 20


def _parse_toml(text: str, where: str) -> dict[str, Any]:
    """``tomllib.loads(text)``; every failure is one :class:`ConfigError` naming ``where``."""
    try:
        parsed = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{where}: invalid TOML: {e}") from None
    except RecursionError:
        # tomllib recurses once per nested array / inline table: thousands of levels exhaust
        # the interpreter's stack
        parsed = None
    if parsed is None or _too_deep(parsed):
        raise ConfigError(
            f"{where}: arrays or tables nested more than {MAX_CONFIG_DEPTH} levels deep "
            "(a configuration nests at most 4)"
        )
    return parsed


#: Deeper nesting is refused before anything walks the tree recursively (``[a.b.c...]``
#: headers nest without recursion in tomllib, but copying or validating them would not).
MAX_CONFIG_DEPTH = 32


def _too_deep(tree: Any) -> bool:
    """Whether ``tree`` (dicts and lists) nests deeper than :data:`MAX_CONFIG_DEPTH`; iterative."""
    stack = [(tree, 0)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_CONFIG_DEPTH:
            return True
        children = node.values() if isinstance(node, dict) else node if isinstance(
            node, list) else ()
        stack.extend((c, depth + 1) for c in children if isinstance(c, dict | list))
    return False


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``"a.b.c=VALUE"`` into ``(["a", "b", "c"], value)``; VALUE is a TOML value.

    A VALUE that is not valid TOML is taken as a plain string, so ``robot.name=k2`` works
    without quotes, unless it starts like a TOML array, table or quoted string (``[``, ``{``,
    ``"``, ``'``): then it was meant as one, and the error says why it is not (one line). A
    bare word still meets the key's type: ``robot.wheel_base_m=abc`` is refused by the schema
    as "must be a number".
    """
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override must look like section.key=value, got {text!r}")
    parts = key.split(".")
    if any(not part for part in parts):
        raise ConfigError(f"override key {key!r} has an empty part")
    raw = raw.strip()
    try:
        parsed = tomllib.loads(f"v = {raw}")
    except RecursionError:
        raise ConfigError(
            f"override {key}: {raw[:20]!r}... is not a TOML value (nested too deeply)"
        ) from None
    except tomllib.TOMLDecodeError as e:
        if raw[:1] in ("[", "{", '"', "'"):
            reason = str(e).splitlines()[0] if str(e) else "invalid value"
            raise ConfigError(
                f"override {key}: {raw!r} is not a TOML value ({reason}); arrays look like "
                "[1, 2], tables like {a = 1}, strings like \"text\" (quote the whole --set "
                "argument for the shell)"
            ) from None
        return parts, raw
    if _too_deep(parsed):
        raise ConfigError(f"override {key}: nested more than {MAX_CONFIG_DEPTH} levels deep")
    if set(parsed) != {"v"}:  # "1\nx = 2": a second line is not part of one value
        raise ConfigError(f"override {key}: {raw!r} is more than one TOML value")
    return parts, parsed["v"]


def apply_override(config: Mapping[str, Any], parts: list[str], value: Any) -> dict[str, Any]:
    """A deep copy of ``config`` with ``value`` set at the dotted key ``parts``."""
    out = copy.deepcopy(dict(config))
    node: dict[str, Any] = out
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            where = ".".join(parts[: i + 1])
            raise ConfigError(
                f"override {'.'.join(parts)}: {where} is a value, not a section ([{where}] "
                f"must be a table, got {child!r:.60})"
            )
        node = child
    node[parts[-1]] = value
    return out


def _section(config: Mapping[str, Any], name: str, parent: str = "") -> Mapping[str, Any]:
    """The table at dotted ``name`` below ``config`` (whose own name is ``parent``)."""
    where = f"{parent}.{name}" if parent else name
    node: Any = config
    for part in name.split("."):
        if not isinstance(node, Mapping):
            raise ConfigError(f"[{where}] must be a table")
        node = node.get(part, {})
    if not isinstance(node, Mapping):
        raise ConfigError(f"[{where}] must be a table, got {node!r}")
    return node



def _duration(value: float) -> float:
    if not (math.isfinite(value) and 0 <= value <= MAX_MAGNITUDE):
        raise ValueError(
            f"must be a finite number >= 0 (0 = run until stopped) and <= {MAX_MAGNITUDE:g}, "
            f"got {value}"
        )
    return value


def _port(value: int) -> int:
    if not 0 <= value <= 65535:
        raise ValueError(f"must be a TCP/UDP port 0..65535, got {value}")
    return value


#: Any int, checked as a port with the message tests and users know.
_PortKey = Annotated[int, Strict(), AfterValidator(_port)]


def _framing(value: str) -> str:
    try:
        serial_bits_per_byte(value)
    except ValueError:
        raise ValueError(f"must be {FRAMING_RULE}, got {value!r}") from None
    return value


#: A UART's character framing, "8N1" style (runtime/wire.py serial_bits_per_byte).
_Framing = Annotated[Str, AfterValidator(_framing)]


def _can_bitrate(value: int) -> int:
    if not 1 <= value <= 1_000_000:
        raise ValueError(f"must be a classical CAN bit rate 1..1000000 bit/s, got {value}")
    return value


_CanBitrate = Annotated[int, Strict(), AfterValidator(_can_bitrate)]

# The wire-timing keys (docs/wire-timing.md) have defaults, default.toml's: configurations and
# recordings from before they existed still load.


# -- exposure: what listens where ---------------------------------------------------------------

def is_loopback_host(host: str) -> bool:
    """Whether ``host`` names this machine's loopback only (``127.0.0.0/8``, ``::1``,
    ``localhost``). Names are not resolved: any other name, ``""`` and ``0.0.0.0`` / ``::``
    (every interface) count as reachable from the network."""
    host = host.strip().strip("[]").lower()
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host.partition("%")[0]).is_loopback
    except ValueError:
        return False


#: Zenoh link protocols whose locator is not a network address (a path, a device).
_LOCAL_ZENOH_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")


def locator_host(locator: str) -> str | None:
    """The host of a Zenoh locator (``tcp/192.168.1.5:7447`` -> ``192.168.1.5``), or None for
    one that is not a network address (``unixsock-stream/path``)."""
    proto, _, address = locator.partition("/")
    if proto in _LOCAL_ZENOH_PROTOCOLS:
        return None
    address = re.split(r"[?#]", address, maxsplit=1)[0]
    host = address.rpartition(":")[0]
    return host.strip("[]")


def _channel_name(kind: str, max_len: int) -> Any:
    """A CAN channel / interface name: printable ASCII without spaces, ``<``, ``>`` or ``/``
    (a socketcand channel travels inside ``< open NAME >``; a Linux interface name has at most
    15 characters and no ``/``)."""

    def check(value: str) -> str:
        if not value or len(value) > max_len or not re.fullmatch(r"[!-~]+", value) or any(
            c in value for c in "<>/\\"
        ):
            raise ValueError(
                f"must be a {kind} name of 1..{max_len} printable characters without spaces, "
                f"'<', '>', '/' or '\\', got {value!r}"
            )
        return value

    return AfterValidator(check)


def _virtual_channel(value: str) -> str:
    """A python-can ``virtual`` channel: any name within the process, but printable."""
    if not value or len(value) > 64 or not value.isprintable():
        raise ValueError(f"must be a name of 1..64 printable characters, got {value!r}")
    return value


@section
class RunSettings:
    """``[run]``: how the loop is paced and for how long."""

    clock: Annotated[Str, one_of(CLOCK_NAMES)]          # "realtime" | "fast"
    # simulation seconds; 0 = until SIGINT/SIGTERM (inf is refused with the same message)
    duration_s: Annotated[float, Strict(), Field(allow_inf_nan=True), AfterValidator(_duration)]
    endpoints_file: Str         # "" = do not write one
    # Serve a bus or Zenoh on an address other than loopback (docs/security.md). Defaults to
    # default.toml's false so that configs from before the key existed still load.
    allow_non_loopback: Bool = False

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RunSettings:
        return validate(cls, d, "run")


#: ``[lockstep] on_quiet``: what the loop does when the firmware sends no cycle message.
QUIET_POLICIES = ("wait", "step")
#: ``[lockstep] cycle_bus``: the buses a firmware commands the robot on.
CYCLE_BUSES = ("kteam", "can")


@section
class LockstepSettings:
    """``[lockstep]``: how ``--clock lockstep`` is paced by the firmware (docs/protocols.md,
    "Lockstep")."""

    # Defaults = config/default.toml's, so that a config written before [lockstep] existed
    # still runs in lockstep.
    cycle_bus: Annotated[Str, one_of(CYCLE_BUSES)] = "kteam"  # the bus whose message closes a cycle
    # K-Team: the command letter ("D"); CAN: the DBC message name ("MotorCommand")
    cycle_message: Str = "D"
    period_s: Positive = 0.01   # simulated seconds one cycle advances (a multiple of [sim] dt_s)
    on_quiet: Annotated[Str, one_of(QUIET_POLICIES)] = "wait"  # wait | step (after quiet_timeout_s)
    quiet_timeout_s: Positive = 1.0  # wall s without a cycle message before on_quiet = "step" steps

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LockstepSettings:
        ls = validate(cls, d, "lockstep")
        if ls.cycle_bus == "kteam" and not (len(ls.cycle_message) == 1
                                            and ls.cycle_message.isalpha()):
            raise ConfigError(
                f"[lockstep] 'cycle_message' must be a K-Team command letter such as \"D\" "
                f"when cycle_bus = \"kteam\", got {ls.cycle_message!r}"
            )
        return ls

    def steps_per_cycle(self, dt: float) -> int:
        """Simulation steps in one cycle; ConfigError unless ``period_s`` is a multiple of dt."""
        n = round(self.period_s / dt)
        if n < 1 or abs(n * dt - self.period_s) > 1e-9 * max(1.0, self.period_s):
            raise ConfigError(
                f"[lockstep] 'period_s' must be a whole multiple of [sim] dt_s = {dt:g} s, "
                f"got {self.period_s!r}"
            )
        return n


@section
class CanSettings:
    """``[buses.can]``: the same CAN bus served on several interfaces at once."""

    channel: Annotated[Str, _channel_name("socketcand channel", 64)]
    socketcand: Bool
    socketcand_host: Str
    socketcand_port: _PortKey
    slcan: Bool
    virtual: Bool
    virtual_channel: Annotated[Str, AfterValidator(_virtual_channel)]
    socketcan: Bool
    socketcan_channel: Annotated[Str, _channel_name("network interface", 15)]
    # The CAN database: a path (relative to the working directory), or "" for the DBC shipped
    # with koala-bridge (koala_bridge.core.resources.default_dbc_path). Read only when a CAN
    # bus is served, so a missing file does not matter with every CAN bus off. A default
    # (default.toml's ""): configs and recordings from before the key existed still load.
    dbc: Str = ""
    # --clock lockstep: frames reach clients after their time on the bus, stuffed bits and
    # arbitration by id included (runtime/wire.py CanWire; docs/wire-timing.md)
    wire_timing: Bool = False
    bitrate: _CanBitrate = 500_000   # bit/s of the simulated bus

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CanSettings:
        return validate(cls, d, "buses.can")

    def exposure(self) -> list[str]:
        """What this section serves on a non-loopback address, one description each."""
        if self.socketcand and not is_loopback_host(self.socketcand_host):
            return [f"socketcand listens on {self.socketcand_host or '*'}:{self.socketcand_port} "
                    "([buses.can] socketcand_host): CAN frames, including MotorCommand"]
        return []

    @property
    def enabled(self) -> bool:
        """Whether any CAN interface is served (only then is the DBC read)."""
        return self.socketcand or self.slcan or self.virtual or self.socketcan

    @property
    def dbc_path(self) -> Path:
        """The DBC file to load: ``dbc``, or the shipped one when ``dbc`` is ""."""
        return Path(self.dbc).expanduser() if self.dbc else default_dbc_path()

    def codec(self, needed: bool | None = None) -> KoalaCanCodec:
        """The CAN codec of :attr:`dbc_path`.

        ``needed`` (default: :attr:`enabled`, whether a CAN bus is served) says whether frames
        go on a CAN bus; then a DBC that cannot be loaded is a :class:`ConfigError` naming the
        key. Otherwise the frames are only recorded and fed to the estimator, and a missing or
        broken ``dbc`` falls back to the shipped database: with every CAN bus off, the key
        does not matter.
        """
        import cantools
        from koala_bridge.drivers.can_codec import KoalaCanCodec, load_koala_dbc
        from koala_bridge.drivers.messages import DriverError

        path = self.dbc_path
        try:
            return KoalaCanCodec(load_koala_dbc(path))
        except (OSError, DriverError, ValueError,
                cantools.database.UnsupportedDatabaseFormatError) as e:
            if needed if needed is not None else self.enabled:
                reason = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
                reason = reason.splitlines()[0] if reason else type(e).__name__
                raise ConfigError(
                    f"[buses.can] 'dbc': cannot load the CAN database {str(path)!r}: {reason}"
                ) from None
            log.debug("[buses.can] dbc %s not loaded (%s); no CAN bus is on", path, e)
            return KoalaCanCodec(load_koala_dbc(default_dbc_path()))


@section
class MavlinkSettings:
    """``[buses.mavlink]``: the compass as a MAVLink 2 component."""

    enabled: Bool
    transport: Annotated[Str, one_of(MAVLINK_TRANSPORTS)]  # udp (send) | tcp (listen) | pty
    host: Str
    # udp: where the client listens (the bridge sends there); 0: the bridge listens on a free
    # port instead and answers whoever sends to it (the client connects with udpout:, sends
    # first). tcp: where the bridge listens, 0 a free port. The endpoints file names the port.
    port: _PortKey
    system_id: Annotated[int, Strict(), Field(ge=1, le=255)]
    component_id: Annotated[int, Strict(), Field(ge=1, le=255)]
    heartbeat_hz: Positive
    # MAVLink 2 message signing (docs/security.md "MAVLink signing"); off with "". A file, not
    # the key itself: the resolved configuration is stored in every recording's metadata.
    signing_key_file: Str = ""
    signing_link_id: Annotated[int, Strict(), Field(ge=0, le=255)] = 0
    # with signing on, accept unsigned messages from clients (counted as received) instead of
    # rejecting them; signed messages with a bad signature are always rejected
    signing_accept_unsigned: Bool = False
    # --clock lockstep: messages reach the ground station after their time on a serial telemetry
    # radio link of baud / framing (runtime/wire.py SerialWire; docs/wire-timing.md)
    wire_timing: Bool = False
    baud: PositiveInt = 57600
    framing: _Framing = "8N1"

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> MavlinkSettings:
        return validate(cls, d, "buses.mavlink")

    def exposure(self) -> list[str]:
        """What this section serves on (or sends to) a non-loopback address."""
        if not self.enabled or self.transport == "pty" or is_loopback_host(self.host):
            return []
        if self.transport == "tcp" or self.port == 0:
            return [f"MAVLink listens on {self.transport} {self.host or '*'}:{self.port} "
                    "([buses.mavlink] host)"]
        return [f"MAVLink sends to udp {self.host}:{self.port} and reads the replies "
                "([buses.mavlink] host)"]

    def signing_key(self) -> bytes | None:
        """The 32-byte MAVLink signing key read from :attr:`signing_key_file` (64 hex digits),
        or None when signing is off. A file that cannot be read or does not hold a key is a
        :class:`ConfigError` naming the key (never the file's content)."""
        if not self.signing_key_file:
            return None
        path = Path(self.signing_key_file).expanduser()
        where = f"[buses.mavlink] 'signing_key_file' {str(path)!r}"
        try:
            text = path.read_bytes()[:4096].decode("ascii").strip()
        except OSError as e:
            raise ConfigError(f"{where}: cannot read it: {e.strerror}") from None
        except UnicodeDecodeError:
            text = ""
        if not re.fullmatch(r"[0-9a-fA-F]{64}", text):
            raise ConfigError(
                f"{where} must hold the 32-byte secret key as 64 hex digits (e.g. the output of "
                "`openssl rand -hex 32`, or the sha256 hex digest of a MAVProxy/QGC passphrase)"
            )
        return bytes.fromhex(text)

    def signing(self, unix_time_s: float) -> MavlinkSigning | None:
        """The link's :class:`~koala_bridge.drivers.mavlink_codec.MavlinkSigning` (None: off),
        its timestamps starting at the wall-clock time ``unix_time_s``."""
        key = self.signing_key()
        if key is None:
            return None
        from koala_bridge.drivers.mavlink_codec import MavlinkSigning, signing_timestamp

        return MavlinkSigning(key, self.signing_link_id, signing_timestamp(unix_time_s),
                              accept_unsigned=self.signing_accept_unsigned)

    def client_url(self, pty_path: str | None = None, bound_port: int | None = None) -> str:
        """The pymavlink connection string a client uses to receive this stream (``udpout:``
        when the bridge listens on a UDP port it picked: the client sends first, e.g. a
        HEARTBEAT, and the bridge answers it)."""
        if self.transport == "udp" and self.port == 0:
            if bound_port is None:
                raise ValueError("a UDP MAVLink link on port 0 needs the port it bound")
            return f"udpout:{self.host}:{bound_port}"
        if self.transport == "udp":
            return f"udpin:{self.host}:{self.port}"
        if self.transport == "tcp":
            return f"tcp:{self.host}:{bound_port if bound_port is not None else self.port}"
        if pty_path is None:
            raise ValueError("a pty MAVLink link needs its path")
        return pty_path


@section
class KteamSettings:
    """``[buses.kteam]``: the K-Team ASCII protocol server on a pty."""

    enabled: Bool
    max_speed: PositiveInt      # largest |speed| K-Team D accepts, pulses per speed unit
    dialect: Annotated[Str, one_of(KTEAM_DIALECTS)]  # koala1 (classic Koala) | koala25
    # --clock lockstep: replies reach the client after their time on the dialect's serial line
    # (Dialect.line: koala1 38400 8N2, koala25 115200 8N1); docs/wire-timing.md
    wire_timing: Bool = False


@section
class RangefindersSettings:
    """``[buses.rangefinders]``: binary IR / sonar frames on a pty."""

    enabled: Bool
    # --clock lockstep: frames reach the client after their time on a baud / framing line
    wire_timing: Bool = False
    baud: PositiveInt = 115200
    framing: _Framing = "8N1"


@dataclass(frozen=True)
class BusesSettings:
    """``[buses]``: which buses are served, and the motor command watchdog."""

    motor_watchdog_s: float     # 0 = off: a wheel command holds until the next one
    kteam: bool
    kteam_max_speed: int        # largest |speed| K-Team D accepts, pulses per speed unit
    kteam_dialect: str          # which Koala's command set the pty speaks (KTEAM_DIALECTS)
    rangefinders: bool
    can: CanSettings
    mavlink: MavlinkSettings
    # the wire-timing keys of [buses.kteam] and [buses.rangefinders] (docs/wire-timing.md);
    # [buses.can] and [buses.mavlink] keep theirs in can / mavlink
    kteam_wire_timing: bool
    rangefinders_wire_timing: bool
    rangefinders_baud: int      # bit/s
    rangefinders_framing: str   # "8N1" style

    @property
    def kteam_line(self) -> SerialLine:
        """The serial line settings of the K-Team dialect's port (its wire timing's baud and
        framing): koala1 38400 8N2, koala25 115200 8N1."""
        return DIALECTS[self.kteam_dialect].line

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> BusesSettings:
        s = "buses"
        reject_unknown(d, field_names(_BusesTable) + list(_BUS_TABLES), s)
        top = validate(_BusesTable, {k: v for k, v in d.items() if k not in _BUS_TABLES}, s)
        kteam = validate(KteamSettings, _section(d, "kteam", s), f"{s}.kteam")
        ranges = validate(RangefindersSettings, _section(d, "rangefinders", s),
                          f"{s}.rangefinders")
        return cls(
            motor_watchdog_s=top.motor_watchdog_s,
            kteam=kteam.enabled,
            kteam_max_speed=kteam.max_speed,
            kteam_dialect=kteam.dialect,
            rangefinders=ranges.enabled,
            can=CanSettings.from_dict(_section(d, "can", s)),
            mavlink=MavlinkSettings.from_dict(_section(d, "mavlink", s)),
            kteam_wire_timing=kteam.wire_timing,
            rangefinders_wire_timing=ranges.wire_timing,
            rangefinders_baud=ranges.baud,
            rangefinders_framing=ranges.framing,
        )

    def exposure(self) -> list[str]:
        """What the enabled buses serve on (or send to) a non-loopback address."""
        return [*self.can.exposure(), *self.mavlink.exposure()]


#: The sub-tables of ``[buses]``, each its own section.
_BUS_TABLES = ("kteam", "rangefinders", "can", "mavlink")


@section
class _BusesTable:
    """``[buses]``'s own keys (its sub-tables are :data:`_BUS_TABLES`)."""

    motor_watchdog_s: NonNegative   # 0 = off


#: ``proto/address[?metadata][#config]``: a protocol name, then anything but spaces.
_LOCATOR = re.compile(r"[a-z][a-z0-9-]*/[^\s/?#][^\s]*")
#: The link protocols Zenoh knows (zenoh.io "Configuration": endpoints).
ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", *_LOCAL_ZENOH_PROTOCOLS)


def _locators(value: tuple[str, ...]) -> tuple[str, ...]:
    for locator in value:
        proto, _, rest = locator.partition("/")
        if proto in _LOCAL_ZENOH_PROTOCOLS and rest.strip():  # a path or a device
            continue
        if not _LOCATOR.fullmatch(locator):
            problem = "not protocol/host:port"
        elif proto not in ZENOH_PROTOCOLS:
            problem = f"unknown protocol {proto!r} (Zenoh's: {', '.join(ZENOH_PROTOCOLS)})"
        else:
            address = re.split(r"[?#]", locator.split("/", 1)[1], maxsplit=1)[0]
            host, _, port = address.rpartition(":")
            bracketed = host.startswith("[") == host.endswith("]")
            if not host or not bracketed or not port.isdigit() or int(port) > 65535:
                problem = "not host:port with a port 0..65535"
            else:
                continue
        raise ValueError(
            f"must be a list of locators like \"tcp/127.0.0.1:7447\" (protocol/host:port): "
            f"{locator!r} is {problem}"
        )
    return value


_Locators = Annotated[tuple[Str, ...], BeforeValidator(tuples), AfterValidator(_locators)]


def _plain_prefix(value: str) -> str:
    """``""`` (``koala/<robot name>``) or a plain Zenoh key expression: chunks separated by
    single ``/``, none empty, without wildcards (``*``, ``$*``) or Zenoh's reserved ``?#``."""
    if value == "":
        return value
    if (
        any(c in value for c in "*$?#")
        or any(not chunk for chunk in value.split("/"))
        or not value.isprintable()
        or any(c.isspace() for c in value)
    ):
        raise ValueError(
            "must be \"\" (koala/<robot name>) or a plain key expression like \"lab/koala1\": "
            "no '*', '$', '?', '#', spaces, empty chunks ('//') or leading/trailing '/'; "
            f"got {value!r}"
        )
    return value


@section
class ZenohSettings:
    """``[zenoh]``: the session and what it publishes."""

    mode: Annotated[Str, one_of(("peer", "client"))]
    listen: _Locators   # port 0: a free port; the endpoints file names the one bound
    connect: _Locators
    multicast_scouting: Bool
    prefix: Annotated[Str, AfterValidator(_plain_prefix)]   # "" in the file: koala/<robot name>
    pose_rate_hz: Positive      # truth/pose, in simulation time
    status_rate_hz: Positive    # status, in simulation time
    # Zenoh's own configuration file (JSON5), for TLS, authentication and access control;
    # "" = none. The keys above are applied on top of it (they win). docs/security.md.
    config_file: Str = ""
    # Accept commands over Zenoh: the lockstep step and fault-scheduling queryables
    # (docs/protocols.md "Lockstep", docs/faults.md). Off by default, like every remote command.
    remote_commands: Bool = False

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], robot_name: str) -> ZenohSettings:
        z = validate(cls, d, "zenoh")
        # resolved: "" in the file means koala/<robot name>
        return dataclasses.replace(z, prefix=z.prefix or f"koala/{robot_name}")

    def exposure(self) -> list[str]:
        """The listen endpoints on a non-loopback address (connecting out is not listening)."""
        return [
            f"Zenoh listens on {locator} ([zenoh] listen): every topic and the world queryable"
            for locator in self.listen
            if (host := locator_host(locator)) is not None and not is_loopback_host(host)
        ]


@dataclass(frozen=True)
class BridgeSettings:
    """The bridge's typed sections of one configuration."""

    run: RunSettings
    buses: BusesSettings
    zenoh: ZenohSettings
    robot_name: str
    lockstep: LockstepSettings = LockstepSettings()

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> BridgeSettings:
        """The typed sections; a non-loopback listener without ``[run] allow_non_loopback``
        is a :class:`ConfigError` (:meth:`exposure`)."""
        reject_unknown_sections(config)
        robot = _section(config, "robot")
        name = robot.get("name", "koala")
        if (not isinstance(name, str) or not name or not name.isprintable()
                or any(c.isspace() or c in "/*$?#\\" for c in name)):
            raise ConfigError(f"[robot] 'name' must be a plain word, got {name!r}")
        settings = cls(
            run=RunSettings.from_dict(_section(config, "run")),
            buses=BusesSettings.from_dict(_section(config, "buses")),
            zenoh=ZenohSettings.from_dict(_section(config, "zenoh"), name),
            robot_name=name,
            lockstep=LockstepSettings.from_dict(_section(config, "lockstep")),
        )
        exposed = settings.exposure()
        if exposed and not settings.run.allow_non_loopback:
            more = f" (and {len(exposed) - 1} more)" if len(exposed) > 1 else ""
            raise ConfigError(
                f"{exposed[0]}{more}: not loopback, so reachable from the network; set "
                "[run] allow_non_loopback = true to mean it (docs/security.md), or use "
                "127.0.0.1"
            )
        return settings

    def exposure(self) -> list[str]:
        """Everything this configuration serves on an address other than loopback, one line
        each (empty for the shipped configuration). The service logs each as a WARNING when
        it opens it; :meth:`from_config` refuses them unless ``[run] allow_non_loopback``."""
        return [*self.buses.exposure(), *self.zenoh.exposure()]


def reject_unknown_sections(config: Mapping[str, Any]) -> None:
    """Raise :class:`ConfigError` for a top-level key that is not one of :data:`SECTIONS`,
    suggesting the nearest (a misspelt ``[bueses]`` must not be ignored silently), or that is
    not a table."""
    for key, value in config.items():
        if key not in SECTIONS:
            near = difflib.get_close_matches(key, SECTIONS, n=1)
            hint = f"did you mean [{near[0]}]?" if near else f"valid: {', '.join(SECTIONS)}"
            raise ConfigError(f"unknown section [{key}]; {hint}")
        if key in ("faults", "robots"):     # arrays of tables: runtime/faults.py, fleet_config.py
            continue
        if not isinstance(value, Mapping):
            raise ConfigError(f"[{key}] must be a table, got {value!r}")
