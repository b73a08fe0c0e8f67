"""MAVLink 2 compass codec built on pymavlink's generated ``common`` dialect.

Each link owns one ``MAVLink`` instance (its own sequence numbers and parser state); nothing here
touches ``pymavlink.mavutil``, its globals or the ``MAVLINK20`` environment variable.

Frames: the bridge and :mod:`sim` use FLU body axes (x forward, y left, z up) and microtesla;
MAVLink ``SCALED_IMU.xmag/ymag/zmag`` are FRD body axes (x forward, y right, z down) in
milligauss. 1 uT = 10 mGauss; FLU -> FRD negates y and z. A level compass then reads
``heading = atan2(-ymag, xmag)``, clockwise from magnetic north (:func:`heading_from_frd`).

Signing (MAVLink 2 "Message Signing", https://mavlink.io/en/guide/message_signing.html), off
unless a :class:`MavlinkSigning` is given: the encoder signs every packet (SHA-256 of the secret
key and the packet, 48 bits, with a link id and a 48-bit timestamp in 10 us since 2015-01-01
that grows with every packet); the decoder then accepts a client's packet only with a valid
signature whose timestamp is newer than the last one of that (link, system, component) stream,
or, with ``accept_unsigned``, an unsigned one. Anything else is a reject (counted, never
raised). These are pymavlink's own semantics (``MAVLink.check_signature``): a pymavlink peer
WITHOUT the key does not check signatures at all and reads signed packets as usual, so signing
authenticates the packets for peers that hold the key; it does not hide them.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import math
import re
from dataclasses import dataclass, field

from koala_bridge.drivers.messages import CompassSample, MavlinkHeartbeat, Reject, RejectReason
from pymavlink.dialects.v20 import common as mavlink2

__all__ = [
    "MG_PER_UT",
    "CompassDecoder",
    "CompassEncoder",
    "MavlinkIdentity",
    "MavlinkSigning",
    "signing_timestamp",
    "flu_ut_to_frd_mgauss",
    "frd_mgauss_to_flu_ut",
    "heading_from_frd",
]

MG_PER_UT = 10.0
"""Milligauss per microtesla (1 G = 1e-4 T)."""
_INT16 = (-32768, 32767)


@dataclass(frozen=True, slots=True)
class MavlinkIdentity:
    """Who the compass says it is in its HEARTBEAT.

    Defaults: system 1, component ``MAV_COMP_ID_IMU`` (200), type ``MAV_TYPE_GROUND_ROVER``,
    autopilot ``MAV_AUTOPILOT_INVALID`` (the MAVLink rule for components that are not flight
    controllers), state ``MAV_STATE_ACTIVE``.
    """

    system_id: int = 1
    component_id: int = mavlink2.MAV_COMP_ID_IMU
    mav_type: int = mavlink2.MAV_TYPE_GROUND_ROVER
    autopilot: int = mavlink2.MAV_AUTOPILOT_INVALID
    system_status: int = mavlink2.MAV_STATE_ACTIVE


#: 2015-01-01T00:00:00Z as a Unix time: the epoch of MAVLink signing timestamps.
SIGNING_EPOCH_UNIX_S = 1_420_070_400


def signing_timestamp(unix_time_s: float) -> int:
    """A MAVLink signing timestamp (10 us units since 2015-01-01 UTC) for a Unix time."""
    return max(0, int((unix_time_s - SIGNING_EPOCH_UNIX_S) * 100_000))


@dataclass(frozen=True, slots=True)
class MavlinkSigning:
    """MAVLink 2 signing of one link.

    Attributes:
        secret_key: the 32-byte shared secret.
        link_id: the link id written into this side's signatures (0..255).
        initial_timestamp: the first timestamp this side signs with, and the reference a new
            incoming stream may lag by at most one minute (:func:`signing_timestamp` of the wall
            clock at start: the spec asks for a timestamp that never goes back).
        accept_unsigned: accept unsigned incoming packets (counted as unsigned) instead of
            rejecting them; a packet with a bad signature is always rejected.
    """

    secret_key: bytes = field(repr=False)
    link_id: int = 0
    initial_timestamp: int = 0
    accept_unsigned: bool = False

    def __post_init__(self) -> None:
        if len(self.secret_key) != 32:
            raise ValueError(f"a MAVLink signing key has 32 bytes, got {len(self.secret_key)}")
        if not 0 <= self.link_id <= 255:
            raise ValueError(f"link_id must be 0..255, got {self.link_id}")

    def state(self, sign_outgoing: bool) -> mavlink2.MAVLinkSigning:
        """pymavlink's signing state for a ``MAVLink`` object of this link."""
        st = mavlink2.MAVLinkSigning()
        st.secret_key = self.secret_key
        st.link_id = self.link_id
        st.timestamp = self.initial_timestamp
        st.sign_outgoing = sign_outgoing
        if self.accept_unsigned:
            st.allow_unsigned_callback = _accept_unsigned
        return st


def _accept_unsigned(mav: mavlink2.MAVLink, msg_id: int) -> bool:
    """pymavlink asks this for an unsigned packet AND for one whose signature failed; only the
    first is accepted (:func:`_check_signature` marks the second)."""
    return not mav.__dict__.pop(_BAD_SIGNATURE, False)


_BAD_SIGNATURE = "_koala_bad_signature"


def flu_ut_to_frd_mgauss(x_ut: float, y_ut: float, z_ut: float) -> tuple[int, int, int]:
    """FLU microtesla -> FRD milligauss, rounded and saturated to int16 (the SCALED_IMU type)."""
    return (_int16(x_ut * MG_PER_UT), _int16(-y_ut * MG_PER_UT), _int16(-z_ut * MG_PER_UT))


def frd_mgauss_to_flu_ut(xmag: int, ymag: int, zmag: int) -> tuple[float, float, float]:
    """FRD milligauss -> FLU microtesla (inverse of :func:`flu_ut_to_frd_mgauss` up to rounding)."""
    return (xmag / MG_PER_UT, -ymag / MG_PER_UT, -zmag / MG_PER_UT)


def heading_from_frd(xmag: float, ymag: float) -> float:
    """Magnetic heading of a level compass, radians clockwise from magnetic north, in [0, 2*pi)."""
    return math.atan2(-ymag, xmag) % math.tau


class CompassEncoder:
    """Encodes HEARTBEAT and SCALED_IMU for one outgoing link.

    Only the ``xmag/ymag/zmag`` and ``time_boot_ms`` fields of SCALED_IMU carry data; acceleration
    and gyro fields are 0 and ``temperature`` is 0 ("no temperature"), as the field definitions
    allow.
    """

    def __init__(
        self, identity: MavlinkIdentity | None = None, signing: MavlinkSigning | None = None
    ) -> None:
        self.identity = identity or MavlinkIdentity()
        self._mav = mavlink2.MAVLink(None, self.identity.system_id, self.identity.component_id)
        if signing is not None:
            self._mav.signing = signing.state(sign_outgoing=True)
        self.signed = signing is not None
        self.messages_encoded = 0

    def heartbeat(self) -> bytes:
        """One HEARTBEAT (msg id 0); the bridge sends it at 1 Hz."""
        ident = self.identity
        msg = self._mav.heartbeat_encode(ident.mav_type, ident.autopilot, 0, 0, ident.system_status)
        return self._pack(msg)

    def scaled_imu(self, sample: CompassSample) -> bytes:
        """One SCALED_IMU (msg id 26) carrying ``sample`` converted to FRD milligauss."""
        xmag, ymag, zmag = flu_ut_to_frd_mgauss(sample.x_ut, sample.y_ut, sample.z_ut)
        time_boot_ms = int(sample.time_boot_ms) & 0xFFFFFFFF
        msg = self._mav.scaled_imu_encode(time_boot_ms, 0, 0, 0, 0, 0, 0, xmag, ymag, zmag, 0)
        return self._pack(msg)

    def _pack(self, msg: mavlink2.MAVLink_message) -> bytes:
        buf = bytes(msg.pack(self._mav))
        self._mav.seq = (self._mav.seq + 1) % 256
        self.messages_encoded += 1
        return buf


class CompassDecoder:
    """Parses a MAVLink byte stream (or datagrams) into compass samples and heartbeats.

    Reads the bridge's output or a real MAVLink compass alike. Bytes that are not a valid MAVLink
    packet (bad CRC, bad magic, truncated, a message id whose CRC cannot be checked) are counted
    in :attr:`rejected` -- once per bad stretch -- never raised. Other valid messages are counted
    in :attr:`ignored`.

    Packets are framed here and only decoded by pymavlink: its own parser drops the whole length a
    false start marker claims when the CRC fails, so one stray byte could swallow the good packets
    behind it, and on a steady stream lock every later packet out. After a bad packet this decoder
    skips only the false marker and searches again (as :class:`RangeFrameDecoder` does); memory
    stays below one maximum-size packet.

    Args:
        system_id / component_id: if set, only samples from this source are returned.
        signing: if set, only packets signed with its key are accepted (or also unsigned ones,
            with ``accept_unsigned``); the others are rejects ("Invalid signature"). One
            signing state serves every datagram, so a replayed (old) timestamp is rejected too.
    """

    def __init__(
        self,
        system_id: int | None = None,
        component_id: int | None = None,
        signing: MavlinkSigning | None = None,
    ) -> None:
        self._signing = None if signing is None else signing.state(sign_outgoing=False)
        self._mav = self._new_parser()
        self._buf = bytearray()
        self._in_bad_run = False
        self.system_id = system_id
        self.component_id = component_id
        self.decoded = 0
        self.ignored = 0
        self.rejected = 0
        self.last_reject: Reject | None = None

    def feed(self, data: bytes) -> list[CompassSample | MavlinkHeartbeat]:
        """Consume a chunk of a byte stream (pty, TCP); a packet may span chunks."""
        self._buf += data
        return self._convert(self._packets(self._buf, final=False))

    def feed_datagram(self, data: bytes) -> list[CompassSample | MavlinkHeartbeat]:
        """Consume one UDP datagram: packets never span datagrams, so a truncated or garbage
        datagram cannot swallow the next one; an incomplete packet is a reject."""
        self._in_bad_run = False
        return self._convert(self._packets(bytearray(data), final=True))

    def _packets(self, buf: bytearray, *, final: bool) -> list[mavlink2.MAVLink_message]:
        """Take the valid packets off the front of ``buf``, skipping what is not one; leave an
        incomplete packet in ``buf`` unless ``final`` (no more bytes will come)."""
        out: list[mavlink2.MAVLink_message] = []
        while buf:
            marker = _MARKERS.search(buf)
            if marker is None:
                self._bad("no MAVLink start marker", buf)
                buf.clear()
                break
            if marker.start():
                self._bad("bytes before a start marker", buf[: marker.start()])
                del buf[: marker.start()]
            size = _packet_size(buf)
            if size is None or len(buf) < size:
                if not final:
                    break
                self._bad("datagram ends inside a packet", buf)
                del buf[:1]
                continue
            try:
                msg = self._decode(buf[:size])
            except mavlink2.MAVError as e:
                self._bad(str(e), buf[:size])
                del buf[:1]
                continue
            del buf[:size]
            self._in_bad_run = False
            out.append(msg)
        return out

    def _decode(self, packet: bytearray) -> mavlink2.MAVLink_message:
        if packet[0] == _MARKER_V2 and packet[2] & ~mavlink2.MAVLINK_IFLAG_SIGNED:
            raise mavlink2.MAVError(f"unknown incompat_flags {packet[2]:#x}")
        msg = self._mav.decode(packet)
        if isinstance(msg, mavlink2.MAVLink_unknown):
            # pymavlink cannot check the CRC of an id it does not know (no CRC_EXTRA), so such
            # a "packet" is as likely a false marker in garbage as a real message.
            raise mavlink2.MAVError(f"unknown message id {msg.get_msgId()}")
        return msg

    def _convert(
        self, messages: list[mavlink2.MAVLink_message]
    ) -> list[CompassSample | MavlinkHeartbeat]:
        out: list[CompassSample | MavlinkHeartbeat] = []
        for msg in messages:
            kind = msg.get_type()
            if not self._wanted(msg):
                self.ignored += 1
                continue
            if kind == "SCALED_IMU":
                x, y, z = frd_mgauss_to_flu_ut(msg.xmag, msg.ymag, msg.zmag)
                out.append(CompassSample(int(msg.time_boot_ms), x, y, z))
            elif kind == "HEARTBEAT":
                out.append(
                    MavlinkHeartbeat(
                        msg.get_srcSystem(), msg.get_srcComponent(), msg.type, msg.autopilot
                    )
                )
            else:
                self.ignored += 1
                continue
            self.decoded += 1
        return out

    def _wanted(self, msg: mavlink2.MAVLink_message) -> bool:
        if self.system_id is not None and msg.get_srcSystem() != self.system_id:
            return False
        return self.component_id is None or msg.get_srcComponent() == self.component_id

    def _bad(self, detail: str, raw: bytes | bytearray) -> None:
        """Count a bad stretch once, and keep what started it (an "Invalid signature" packet
        is then skipped byte by byte; the bytes after its marker are not the cause)."""
        if not self._in_bad_run:
            self.rejected += 1
            self.last_reject = Reject(RejectReason.GARBAGE, detail, bytes(raw[:32]))
        self._in_bad_run = True

    def _new_parser(self) -> mavlink2.MAVLink:
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        if self._signing is not None:
            parser.signing = self._signing
            parser.check_signature = functools.partial(_check_signature, parser)
        return parser


_MARKER_V1 = mavlink2.PROTOCOL_MARKER_V1
_MARKER_V2 = mavlink2.PROTOCOL_MARKER_V2
_MARKERS = re.compile(rb"[\xfd\xfe]")  # PROTOCOL_MARKER_V2, PROTOCOL_MARKER_V1


def _packet_size(buf: bytearray) -> int | None:
    """Size of the packet whose start marker is ``buf[0]`` (header, payload, CRC, signature),
    or None while its header is incomplete."""
    if buf[0] == _MARKER_V1:
        return mavlink2.HEADER_LEN_V1 + buf[1] + 2 if len(buf) >= 2 else None
    if len(buf) < 3:
        return None
    signed = buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED
    signature = mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0
    return mavlink2.HEADER_LEN_V2 + buf[1] + 2 + signature


def _check_signature(
    mav: mavlink2.MAVLink, msgbuf: bytearray, src_system: int, src_component: int
) -> bool:
    """pymavlink's ``MAVLink.check_signature`` with the signature checked FIRST.

    pymavlink 2.4 records a stream's timestamp before it compares the signature, so one
    unauthenticated packet with a timestamp in the future makes every later genuine packet of
    that (link, system, component) stream "old" and rejected. Here only a packet whose
    signature is valid moves the stream's timestamp; the rules are otherwise the spec's: newer
    than the stream's last timestamp, and a new stream at most one minute behind ours.
    """
    signing = mav.signing
    assert signing.secret_key is not None
    mav.__dict__[_BAD_SIGNATURE] = True  # until proven good (read by _accept_unsigned)
    digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
    if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
        return False
    timestamp = int.from_bytes(msgbuf[-12:-6], "little")
    stream = (msgbuf[-13], src_system, src_component)
    last = signing.stream_timestamps.get(stream)
    if last is not None and timestamp <= last:
        return False  # a replay, or an older packet
    if last is None and timestamp + _ONE_MINUTE < signing.timestamp:
        return False
    del mav.__dict__[_BAD_SIGNATURE]
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True


#: One minute in signing-timestamp units (10 us): how far a new stream may lag (the spec's rule).
_ONE_MINUTE = 6_000_000


def _int16(value: float) -> int:
    return max(_INT16[0], min(_INT16[1], round(value)))
