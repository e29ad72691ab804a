"""A minimal Foxglove WebSocket client (the `foxglove.sdk.v1` subprotocol) for the live view's
test and benchmark: it subscribes to channels by topic and records what arrives.

Protocol (foxglove/ws-protocol): the server sends JSON text frames (`serverInfo`, `advertise`
with the channels' ids and topics); the client answers `subscribe` with its own subscription ids;
message data then comes as binary frames: opcode 0x01, uint32 subscription id, uint64 log time
(ns), payload, little endian.
"""
from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

SUBPROTOCOL = 'foxglove.sdk.v1'
_MESSAGE_DATA = 0x01
_HEADER = struct.Struct('<BIQ')


@dataclass
class Received:
    """What one client got: per topic the (wall receive time, payload bytes) of each message,
    the advertised channels and the first payload of each topic."""

    channels: dict[str, dict] = field(default_factory=dict)
    arrivals: dict[str, list[tuple[float, int]]] = field(default_factory=dict)
    first: dict[str, bytes] = field(default_factory=dict)

    def rate_hz(self, topic: str, duration_s: float) -> float:
        return len(self.arrivals.get(topic, ())) / duration_s


async def _receive(url: str, topics: Iterable[str] | None, duration_s: float,
                   until_each: bool, stop: threading.Event | None) -> Received:
    import websockets  # noqa: PLC0415 - only the test and the bench use the client
    from websockets.exceptions import ConnectionClosed  # noqa: PLC0415
    from websockets.typing import Subprotocol  # noqa: PLC0415

    want = set(topics) if topics is not None else None
    got = Received()
    by_sub: dict[int, str] = {}
    async with websockets.connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)], max_size=None,
                                  open_timeout=20) as ws:
        t_end = time.monotonic() + duration_s
        while (left := t_end - time.monotonic()) > 0:
            if stop is not None and stop.is_set():
                break
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=min(left, 0.5))
            except TimeoutError:
                continue
            except ConnectionClosed:           # the server went away: what came is the result
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get('op') == 'advertise':
                    subs = []
                    for ch in msg['channels']:
                        if want is not None and ch['topic'] not in want:
                            continue
                        got.channels[ch['topic']] = ch
                        sub_id = len(by_sub) + 1
                        by_sub[sub_id] = ch['topic']
                        got.arrivals.setdefault(ch['topic'], [])
                        subs.append({'id': sub_id, 'channelId': ch['id']})
                    if subs:
                        await ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subs}))
                continue
            if not frame or frame[0] != _MESSAGE_DATA:
                continue
            _, sub_id, _log_time = _HEADER.unpack_from(frame)
            topic = by_sub.get(sub_id)
            if topic is None:
                continue
            got.arrivals[topic].append((time.monotonic(), len(frame) - _HEADER.size))
            got.first.setdefault(topic, bytes(frame[_HEADER.size:]))
            if until_each and want is not None and all(got.arrivals.get(t) for t in want):
                break
    return got


def receive(url: str, *, topics: Iterable[str] | None = None, duration_s: float = 10.0,
            until_each: bool = False, stop: threading.Event | None = None) -> Received:
    """Connect to `url`, subscribe to `topics` (all when None) and record for `duration_s`,
    until `stop` is set or the server closes; with `until_each`, return as soon as every
    topic got a message."""
    return asyncio.run(_receive(url, topics, duration_s, until_each, stop))
