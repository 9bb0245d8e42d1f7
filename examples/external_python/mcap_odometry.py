"""mcap_odometry: dead reckoning read straight from a recording, a program that does not know slamreplay.

It reads the MCAP file with the ``mcap`` library and decodes each message with protobuf, from the schema
the recording carries (``foxglove.PoseInFrame`` on ``/odom``: the cumulative odometry pose), composes the
odometry increments (each scaled by ``scale`` from the JSON config file, default 1) and writes a TUM
trajectory that starts at its own origin.

    python mcap_odometry.py RECORDING.mcap OUT.tum [CONFIG.json]

Exit status 0 on success, 1 when the recording has no /odom, 2 on bad usage.
"""

from __future__ import annotations

import json
import math
import sys

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

VERSION = "mcap_odometry 1.0"


def message_class(schema):  # a protobuf class made from the recording's own schema
    """The protobuf class of an MCAP schema (a serialized FileDescriptorSet, as Foxglove's schemas are)."""
    files = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for fd in files.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


def yaw_of(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def main(argv: list[str]) -> int:
    if argv[1:] == ["--version"]:
        print(VERSION)
        return 0
    if len(argv) not in (3, 4):
        print("usage: mcap_odometry.py RECORDING.mcap OUT.tum [CONFIG.json]", file=sys.stderr)
        return 2
    scale = 1.0
    if len(argv) == 4:
        with open(argv[3]) as f:
            scale = float(json.load(f).get("scale", 1.0))
    classes = {}
    rows = []
    prev = None
    x = y = th = 0.0
    with open(argv[1], "rb") as f:
        for schema, _channel, message in make_reader(f).iter_messages(topics=["/odom"], log_time_order=True):
            if schema.id not in classes:
                classes[schema.id] = message_class(schema)
            pose = classes[schema.id].FromString(message.data).pose
            ox, oy, oth = pose.position.x, pose.position.y, yaw_of(pose.orientation)
            if prev is not None:
                px, py, pth = prev
                c, s = math.cos(pth), math.sin(pth)
                dx = (c * (ox - px) + s * (oy - py)) * scale  # the increment in the previous odometry frame
                dy = (-s * (ox - px) + c * (oy - py)) * scale
                x, y = x + math.cos(th) * dx - math.sin(th) * dy, y + math.sin(th) * dx + math.cos(th) * dy
                th = math.atan2(math.sin(th + oth - pth), math.cos(th + oth - pth))
            prev = (ox, oy, oth)
            t = message.log_time
            rows.append(f"{t // 1_000_000_000}.{t % 1_000_000_000:09d} {x:.12g} {y:.12g} 0 0 0 "
                        f"{math.sin(th / 2):.12g} {math.cos(th / 2):.12g}\n")
    if not rows:
        print(f"mcap_odometry: {argv[1]} has no /odom messages", file=sys.stderr)
        return 1
    with open(argv[2], "w") as out:
        out.write("# timestamp x y z qx qy qz qw\n" + "".join(rows))
    print(f"mcap_odometry: {len(rows)} poses, scale {scale:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
