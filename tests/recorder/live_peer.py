"""A robot for the live-recording tests: the Foxglove SDK's WebSocket server publishing an MCAP file's messages.

``python live_peer.py FILE.mcap --port-file P --sent-file S [--speed X] [--drop-after N --drop-for SECONDS]``

Each channel of the file is served as it is (topic, message encoding, schema name, encoding and bytes):
a slamreplay recording gives Foxglove protobuf channels, an MCAP-storage ROS 2 bag gives ``cdr`` channels with
``ros2msg`` schemas, as ``foxglove_bridge`` serves them. A JSON channel in a schema slamreplay does not read
(``/diagnostics``) is served beside them. The messages go out in log-time order, ``--speed`` times faster than
recorded (0: as fast as the server takes them), once every channel has a subscriber; the server's log time of
each is its log time in the file. ``--drop-after N`` stops the server after N messages and starts it again on the
same port ``--drop-for`` seconds later, as a robot whose link drops. The counts of messages sent per topic
(to a subscriber) are written to ``--sent-file`` as JSON at the end, and the port to ``--port-file`` at the start.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import foxglove
from foxglove import Channel, Schema
from mcap.reader import make_reader

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: its waits stretch as the tests' do
from patience import deadline as give_up_at

UNKNOWN = "/diagnostics"


class _Subscriptions:
    """The server's listener: which channels a client subscribed to (a new server starts with none)."""

    def __init__(self) -> None:
        self.topics: set[str] = set()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.topics.add(channel.topic)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self.topics.discard(channel.topic)

    def wait(self, timeout_s: float = 20.0) -> None:
        """Until a client has subscribed (to what it wants: one subscribe message for all of them); ``timeout_s``
        on an idle machine, stretched by its load as the tests' own waits are (tests/patience.py)."""
        deadline = give_up_at(timeout_s)
        while not self.topics:
            if time.monotonic() > deadline:
                sys.exit("live_peer: nobody subscribed")
            time.sleep(0.01)
        time.sleep(0.2)  # the rest of the subscription reaches the server's send loop


def _start(port: int, subs: _Subscriptions) -> Any:
    return foxglove.start_server(port=port, message_backlog_size=1 << 16, server_listener=subs)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("mcap")
    p.add_argument("--port-file", required=True)
    p.add_argument("--sent-file", required=True)
    p.add_argument("--speed", type=float, default=0.0)
    p.add_argument("--drop-after", type=int, default=0)
    p.add_argument("--drop-for", type=float, default=0.0)
    p.add_argument("--linger-s", type=float, default=30.0, help="keep serving after the last message")
    a = p.parse_args()
    with open(a.mcap, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        items = [(schema, channel, message) for schema, channel, message in reader.iter_messages(log_time_order=True)]
    channels: dict[int, Channel] = {}
    for cid, ch in summary.channels.items():
        s = summary.schemas[ch.schema_id]
        channels[cid] = Channel(ch.topic, schema=Schema(name=s.name, encoding=s.encoding, data=s.data),
                                message_encoding=ch.message_encoding)
    unknown = Channel(UNKNOWN, schema=Schema(name="my_robot.Diagnostics", encoding="jsonschema",
                                             data=b'{"type": "object"}'), message_encoding="json")
    subs = _Subscriptions()
    server = _start(0, subs)
    port = server.port
    Path(a.port_file + ".tmp").write_text(str(port))
    os.replace(a.port_file + ".tmp", a.port_file)
    subs.wait()
    sent: dict[str, int] = {}
    t0_file, t0 = items[0][2].log_time if items else 0, time.monotonic()
    for n, (_, ch, msg) in enumerate(items):
        if a.drop_after and n == a.drop_after:
            time.sleep(0.5)  # what the server queued reaches the client: only the link drops, no message with it
            server.stop()
            time.sleep(a.drop_for)
            subs = _Subscriptions()
            server = _start(port, subs)
            subs.wait()
            t0_file, t0 = msg.log_time, time.monotonic()
        if a.speed > 0:
            delay = (msg.log_time - t0_file) / 1e9 / a.speed - (time.monotonic() - t0)
            if delay > 0:
                time.sleep(delay)
        if ch.topic in subs.topics:  # sent to a subscriber, not only logged
            sent[ch.topic] = sent.get(ch.topic, 0) + 1
        channels[ch.id].log(msg.data, log_time=msg.log_time)
        if n % 10 == 0:
            unknown.log({"n": n})
    Path(a.sent_file + ".tmp").write_text(json.dumps(sent))
    os.replace(a.sent_file + ".tmp", a.sent_file)
    time.sleep(a.linger_s)
    server.stop()


if __name__ == "__main__":
    main()
