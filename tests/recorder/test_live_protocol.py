"""`record live`'s protocol client and channel plan: advertise parsing, subprotocols, topic patterns, mapping."""

from __future__ import annotations

import base64
import contextlib
import json
import struct
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore
from websockets.sync.server import serve

from slamreplay.recorder.codec.live import message_decoder
from slamreplay.recorder.errors import CodecError, RecorderError
from slamreplay.recorder.importers.foxglove_live import LiveOptions, LiveRecording
from slamreplay.recorder.importers.foxglove_ws import ChannelInfo, channel_info, parse_binary, parse_text
from slamreplay.recorder.importers.live_plan import Conversion, compile_patterns, plan_channels
from slamreplay.recorder.importers.ros2bag import tf_poses
from slamreplay.recorder.importers.tf_tree import TfTree
from slamreplay.recorder.messages import OdometryPose
from slamreplay.replay.engine.reader import RecordingReader


def _ch(cid: int, topic: str, encoding: str, schema_name: str, schema_encoding: str = "") -> ChannelInfo:
    return channel_info({"id": cid, "topic": topic, "encoding": encoding, "schemaName": schema_name,
                         "schemaEncoding": schema_encoding or None, "schema": ""})


def test_advertise_schemas_decode_by_their_encoding_and_default_from_the_message_encoding() -> None:
    """Binary schemas (protobuf) arrive base64-encoded, text ones (ros2msg) as they are; no schemaEncoding: from
    the message encoding, as older bridges send it."""
    fds = b"\x0a\x05hello"
    pb = channel_info({"id": 1, "topic": "/a", "encoding": "protobuf", "schemaName": "foxglove.PoseInFrame",
                       "schema": base64.b64encode(fds).decode()})
    assert (pb.schema_encoding, pb.schema, pb.problem) == ("protobuf", fds, None)
    ros = channel_info({"id": 2, "topic": "/b", "encoding": "cdr", "schemaName": "nav_msgs/msg/Odometry",
                        "schema": "float64 x"})
    assert (ros.schema_encoding, ros.schema) == ("ros2msg", b"float64 x")
    bad = channel_info({"id": 3, "topic": "/c", "encoding": "protobuf", "schemaName": "x", "schema": "%%%"})
    assert bad.problem is not None and "not valid base64" in bad.problem
    event = parse_text(json.dumps({"op": "advertise", "channels": [{"id": 1}]}))  # no topic: not the protocol
    assert getattr(event, "level", None) == 2
    data = parse_binary(struct.pack("<BIQ", 1, 7, 123) + b"payload", 5)
    assert data is not None and (data.subscription_id, data.log_time_ns, data.payload) == (7, 123, b"payload")
    assert parse_binary(struct.pack("<BQ", 2, 123), 5) is None  # time: not a message


def test_topic_patterns_are_names_globs_or_regular_expressions() -> None:
    """`--topics /odom '/robot/*' 're:/cam.*/image'`: names, globs, regexes on the whole topic."""
    sel = compile_patterns(["/odom", "/robot/*", "re:/cam.*/image"])
    assert [t for t in ("/odom", "/odom2", "/robot/pose", "/camera/left/image", "/camera/left/image/x")
            if sel(t)] == ["/odom", "/robot/pose", "/camera/left/image"]
    assert compile_patterns([])("/anything")
    with pytest.raises(RecorderError, match=r"--topics 're:\(': not a regular expression"):
        compile_patterns(["re:("])


def test_channels_map_as_named_first_then_by_type_and_the_rest_are_skipped_with_a_reason() -> None:
    """A channel named as a logical topic keeps it; another pose goes to the next free one only by --topic-map."""
    chans = [_ch(1, "/a_pose", "protobuf", "foxglove.PoseInFrame"),
             _ch(2, "/odom", "protobuf", "foxglove.PoseInFrame"),
             _ch(3, "/markers", "protobuf", "foxglove.SceneUpdate"), _ch(4, "/tf", "cdr", "tf2_msgs/msg/TFMessage"),
             _ch(5, "/blob", "flatbuffer", "x.Blob"), _ch(6, "/scan", "cdr", "sensor_msgs/msg/LaserScan", "ros2idl")]
    plans = {p.channel.topic: p for p in plan_channels(chans, compile_patterns([]), {}, {})}
    assert plans["/odom"].maps_to == "/odom" and plans["/odom"].note == "as named"
    assert plans["/a_pose"].maps_to is None and "--topic-map /a_pose=/odom" in plans["/a_pose"].note
    assert "foxglove.SceneUpdate is not one slamreplay reads" in plans["/markers"].note
    assert plans["/tf"].note == "not needed: odometry comes from /odom and no --ground-truth-frame was given"
    assert "flatbuffer encoding is not read" in plans["/blob"].note
    assert "ros2idl schema" in plans["/scan"].note
    mapped = {p.channel.topic: p.maps_to for p in plan_channels(chans, compile_patterns([]),
                                                                {"/a_pose": "/ground_truth/pose"}, {})}
    assert mapped["/a_pose"] == "/ground_truth/pose" and mapped["/odom"] == "/odom"
    with pytest.raises(RecorderError, match=r"--topic-map /markers=/odom: a protobuf foxglove.SceneUpdate channel "
                                            r"can become nothing"):
        plan_channels(chans, compile_patterns([]), {"/markers": "/odom"}, {})
    with pytest.raises(RecorderError, match=r"--topic-map /a_pose=/odom: /odom comes from /odom already"):
        plan_channels(chans, compile_patterns([]), {"/a_pose": "/odom"}, {"/odom": "/odom"})


TF_MSG, LASER_MSG = "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/LaserScan"


def test_tf_channels_give_odometry_and_ground_truth_as_the_bag_importer_decides() -> None:
    """/tf gives odometry when no channel does and ground truth with a frame; /tf_static the links of those."""
    tf, tf_static = _ch(1, "/tf", "cdr", TF_MSG), _ch(2, "/tf_static", "cdr", TF_MSG)
    odom, scan = _ch(3, "/wheel/odom", "cdr", "nav_msgs/msg/Odometry"), _ch(4, "/scan", "cdr", LASER_MSG)
    taken: dict[str, str] = {}
    plans = {p.channel.topic: p for p in plan_channels([tf, tf_static], compile_patterns([]), {}, taken)}
    assert (plans["/tf"].maps_to, plans["/tf"].composes) == ("transform tree", ("/odom",))
    assert plans["/tf"].note == "odometry composed through the tree" and taken == {"/odom": "/tf"}
    assert plans["/tf_static"].note == "odometry composed through the tree"
    # an odometry channel (advertised with it, named after /tf) keeps /odom; /tf gives ground truth in map
    plans = {p.channel.topic: p for p in plan_channels([odom, tf, tf_static, scan], compile_patterns([]), {}, {},
                                                       ground_truth_frame="map")}
    assert plans["/wheel/odom"].maps_to == "/odom" and plans["/tf"].composes == ("/ground_truth/pose",)
    assert plans["/tf_static"].note == "ground truth and the laser's mounting composed through the tree"
    # advertised later, an odometry channel finds /odom taken by /tf
    later = plan_channels([odom], compile_patterns([]), {}, taken)
    assert later[0].maps_to is None and "/odom comes from /tf" in later[0].note
    other = plan_channels([_ch(5, "/robot/tf", "cdr", TF_MSG)], compile_patterns([]), {}, {})
    assert other[0].maps_to is None and "from /tf and /tf_static only" in other[0].note


def test_poses_composed_tick_by_tick_are_those_of_the_whole_tree() -> None:
    """Odometry and ground truth composed each second, the tree pruned between, equal `record ros2`'s from the
    whole tree: every stamp once, the same poses (a turning robot, map -> odom drifting)."""
    rng = np.random.default_rng(5)
    whole, live = TfTree(), Conversion(ground_truth_frame="map")
    live.composed = {"/odom": None, "/ground_truth/pose": None}
    got: list[Any] = []
    for k in range(300):  # 30 s at 10 Hz, composed every 10 messages (a second)
        ns = 1_000_000_000 + k * 100_000_000
        yaw, drift = 0.05 * k, rng.normal(0, 0.01, 3)
        for tree in (whole, live.tree):
            tree.add("odom", "base_link", ns, (0.1 * k, 0.02 * k * k / 300, 0.0),
                     (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)), static=False)
            tree.add("map", "odom", ns, (drift[0], drift[1], 0.0), (0.0, 0.0, np.sin(drift[2] / 2),
                                                                    np.cos(drift[2] / 2)), static=False)
        if k % 10 == 9:
            out, problems = live.compose()
            assert problems == []
            got += out
    assert len(live.tree._edges["base_link"].stamps) < 3  # pruned: a long stream's tree stays small
    for topic, frame in (("/odom", "odom"), ("/ground_truth/pose", "map")):
        want = tf_poses(whole, topic, frame, "base_link")
        mine = [m for t, m, _ in got if t == topic]
        assert len(mine) == len(want) == 300
        for a, b in zip(want, mine, strict=True):
            assert (a.stamp_ns, type(a)) == (b.stamp_ns, type(b))
            assert np.allclose([a.x_m, a.y_m, a.yaw_rad], [b.x_m, b.y_m, b.yaw_rad], atol=1e-9)
    none = Conversion(ground_truth_frame="world")
    none.composed = {"/ground_truth/pose": None}
    none.tree.add("odom", "base_link", 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), static=False)
    assert none.compose() == ([], ["/ground_truth/pose from /tf: the tf tree has no frame 'world' (frames: "
                                   "base_link, odom): pass --ground-truth-frame with one of them"])


def test_json_channels_in_a_foxglove_schema_are_read_with_their_sec_nsec_timestamps() -> None:
    """A JSON foxglove.PoseInFrame (as the Foxglove SDK logs a dict) is read like the protobuf one."""
    dec = message_decoder("/odom", OdometryPose, "json", "foxglove.PoseInFrame", "jsonschema", b"{}")
    msg = dec(json.dumps({"timestamp": {"sec": 3, "nsec": 500}, "frame_id": "odom", "pose": {
        "position": {"x": 1.5, "y": -2.0, "z": 0.0}, "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}}}).encode(), 9)
    assert msg == OdometryPose(3_000_000_500, 1.5, -2.0, 0.0)
    with pytest.raises(CodecError, match=r"/odom: a JSON foxglove.PoseInFrame message is invalid"):
        dec(b"[1, 2", 9)


ODOM_MSGDEF_TYPE = "nav_msgs/msg/Odometry"


@pytest.fixture
def legacy_bridge() -> Iterator[str]:
    """A server that speaks only ``foxglove.websocket.v1`` and sends no schemaEncoding, as older foxglove_bridge
    releases do: one cdr nav_msgs/Odometry channel, three messages after the subscribe."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    msgdef, _ = store.generate_msgdef(ODOM_MSGDEF_TYPE, ros_version=2)
    Odometry = store.types[ODOM_MSGDEF_TYPE]
    H, T = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    P, PC = store.types["geometry_msgs/msg/Pose"], store.types["geometry_msgs/msg/PoseWithCovariance"]
    V, Q = store.types["geometry_msgs/msg/Point"], store.types["geometry_msgs/msg/Quaternion"]
    TW, TC = store.types["geometry_msgs/msg/Twist"], store.types["geometry_msgs/msg/TwistWithCovariance"]
    V3 = store.types["geometry_msgs/msg/Vector3"]
    def odom(i: int) -> bytes:
        msg = Odometry(H(T(10 + i, 0), "odom"), "base_link",
                       PC(P(V(float(i), 0.0, 0.0), Q(0.0, 0.0, 0.0, 1.0)), np.zeros(36)),
                       TC(TW(V3(0.0, 0.0, 0.0), V3(0.0, 0.0, 0.0)), np.zeros(36)))
        return bytes(store.serialize_cdr(msg, ODOM_MSGDEF_TYPE))

    def handler(ws: Any) -> None:
        ws.send(json.dumps({"op": "serverInfo", "name": "legacy", "capabilities": []}))
        ws.send(json.dumps({"op": "advertise", "channels": [{"id": 7, "topic": "/odom", "encoding": "cdr",
                                                              "schemaName": ODOM_MSGDEF_TYPE, "schema": msgdef}]}))
        sub = json.loads(ws.recv())
        assert sub["op"] == "subscribe"
        sid = sub["subscriptions"][0]["id"]
        for i in range(3):
            ws.send(struct.pack("<BIQ", 1, sid, 1000 + i) + odom(i))
        with contextlib.suppress(Exception):  # its close, however it comes
            ws.recv()  # until the client leaves

    with serve(handler, "127.0.0.1", 0, subprotocols=["foxglove.websocket.v1"]) as server:  # type: ignore[list-item]
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        yield f"ws://127.0.0.1:{server.socket.getsockname()[1]}"
        server.shutdown()


def test_a_legacy_foxglove_websocket_v1_bridge_is_recorded(legacy_bridge: str, tmp_path: Path) -> None:
    """The older subprotocol, a schema without schemaEncoding: three odometry messages at their header stamps."""
    lines: list[str] = []
    live = LiveRecording(LiveOptions(url=legacy_bridge, out=tmp_path / "o.mcap", wait_s=2), say=lines.append)
    thread = threading.Thread(target=live.run)
    thread.start()
    for _ in range(200):
        if live.status().messages >= 3:
            break
        threading.Event().wait(0.02)
    live.stop()
    thread.join(10)
    assert "(foxglove.websocket.v1)" in lines[0]
    got = [(e.topic, e.log_time_ns, e.msg) for e in RecordingReader(tmp_path / "o.mcap").messages()]
    assert got == [("/odom", (10 + i) * 10**9, OdometryPose((10 + i) * 10**9, float(i), 0.0, 0.0)) for i in range(3)]
