"""A Foxglove WebSocket client written from the public protocol specification, and protobuf
decoding of Foxglove's schemas from the file descriptor set a channel carries: what a Foxglove
client does, with no foxglove-sdk code on the client side.

The protocol is ``foxglove.websocket.v1``; foxglove-sdk's server names it ``foxglove.sdk.v1``
(the same protocol under a new name): the client offers both, as the Foxglove app does, and the
server picks the new one (docs/foxglove.md). JSON text frames ``serverInfo``, ``advertise``,
``subscribe``; binary frames, opcode 0x01 = message data:
``<u8 op><u32 subscription id><u64 log time ns><payload>``, opcode 0x02 = time (a server with
the ``time`` capability): ``<u8 op><u64 timestamp ns>``."""

from __future__ import annotations

import base64
import json
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
MESSAGE_DATA = 0x01
TIME = 0x02
_HEADER = struct.Struct("<BIQ")
_TIME = struct.Struct("<BQ")


def protobuf_decoder(schema_name: str, descriptor_set: bytes) -> Callable[[bytes], Any]:
    """A function bytes -> protobuf message of ``schema_name`` (``foxglove.SceneUpdate``) from
    the serialized ``FileDescriptorSet`` of a protobuf channel's schema."""
    files = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))
    return cls.FromString


@dataclass
class Received:
    topic: str
    log_time_ns: int
    message: Any


@dataclass
class FoxgloveClient:
    """A client, connected inside ``with``: ``channels`` by topic as advertised,
    ``subscribe(topics)``, ``receive(done, timeout)``; ``times``: the server's time messages
    (ns), in order of arrival."""

    url: str
    ws: ClientConnection = field(init=False)
    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    _subs: dict[int, tuple[str, Callable[[bytes], Any]]] = field(default_factory=dict)
    times: list[int] = field(default_factory=list)

    def __enter__(self) -> FoxgloveClient:
        # close_timeout: the server (foxglove-sdk) ends the TCP connection on a close frame
        # without one of its own (1006); behind a receive queue full of a subscription's data
        # the client only sees that after websockets' default 10 s
        self.ws = connect(self.url, subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
                          open_timeout=30, close_timeout=2,
                          proxy=None).__enter__()  # loopback: never a proxy
        assert self.ws.subprotocol in SUBPROTOCOLS
        return self

    def __exit__(self, *exc: object) -> None:
        self.ws.__exit__(*exc)  # type: ignore[arg-type]

    def _text(self, msg: dict[str, Any]) -> None:
        if msg.get("op") == "serverInfo":
            self.server_info = msg
        elif msg.get("op") == "advertise":
            for ch in msg["channels"]:
                self.channels[ch["topic"]] = ch
        elif msg.get("op") == "unadvertise":
            gone = set(msg["channelIds"])
            self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}

    def wait_advertised(self, topics: list[str], timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not set(topics) <= set(self.channels):
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"not advertised: {set(topics) - set(self.channels)}"
            self._read(remaining, lambda r: None)

    def subscribe(self, topics: list[str]) -> None:
        subs = []
        for topic in topics:
            ch = self.channels[topic]
            sub_id = len(self._subs) + 1
            if ch["encoding"] == "protobuf":
                decode = protobuf_decoder(ch["schemaName"], base64.b64decode(ch["schema"]))
            else:
                assert ch["encoding"] == "json", ch
                decode = json.loads
            self._subs[sub_id] = (topic, decode)
            subs.append({"id": sub_id, "channelId": ch["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _read(self, timeout: float, on_message: Callable[[Received], None]) -> None:
        try:
            frame = self.ws.recv(timeout=timeout)
        except TimeoutError:
            return
        if isinstance(frame, str):
            self._text(json.loads(frame))
            return
        if frame[0] == TIME:
            self.times.append(_TIME.unpack_from(frame)[1])
            return
        if frame[0] != MESSAGE_DATA:
            return  # the rest: not needed here
        _, sub_id, log_time = _HEADER.unpack_from(frame)
        topic, decode = self._subs[sub_id]
        on_message(Received(topic, log_time, decode(frame[_HEADER.size:])))

    def receive(self, done: Callable[[dict[str, list[Received]]], bool],
                timeout: float = 60.0) -> dict[str, list[Received]]:
        """Messages by topic until ``done(messages)`` holds; fails after ``timeout`` s."""
        got: dict[str, list[Received]] = {}
        deadline = time.monotonic() + timeout
        while not done(got):
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"timed out; got {({t: len(v) for t, v in got.items()})}"
            self._read(min(remaining, 1.0), lambda r: got.setdefault(r.topic, []).append(r))
        return got
