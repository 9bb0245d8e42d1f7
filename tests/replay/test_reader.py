"""The ordered reader: one total order, filters, windows, ROS 2 bags, and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer
from ros2_fixtures import write_ros2_bag

from slamreplay.recorder import GroundTruthPose, OdometryPose, RangeBearingScan, Recorder, codec
from slamreplay.recorder.messages import CameraImage
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.errors import ReplayError


def test_order_is_log_time_then_file_position(tmp_path: Path) -> None:
    """Messages written out of time order come back sorted; equal times keep file order."""
    path = tmp_path / "r.mcap"
    with Recorder(path, source={}) as rec:
        rec.write("/odom", OdometryPose(30, 3, 0, 0))
        rec.write("/ground_truth/pose", GroundTruthPose(10, 1, 0, 0))
        rec.write("/odom", OdometryPose(10, 1, 0, 0))
        rec.write("/ground_truth/pose", GroundTruthPose(20, 2, 0, 0))
    got = [(e.log_time_ns, e.topic, e.index) for e in RecordingReader(path).messages()]
    assert got == [(10, "/ground_truth/pose", 0), (10, "/odom", 1), (20, "/ground_truth/pose", 2), (30, "/odom", 3)]


def test_topics_exclude_and_window(tiny_recording: Path) -> None:
    """Topic include/exclude and a [start, end) window on log time."""
    reader = RecordingReader(tiny_recording)
    odom = list(reader.messages(["/odom"]))
    assert len(odom) == 100 and all(e.topic == "/odom" for e in odom)
    no_gt = {e.topic for e in reader.messages(exclude=["/ground_truth/pose"])}
    assert no_gt == {"/odom", "/landmarks/range_bearing", "/ground_truth/landmarks"}
    start, end = 1_000_000_000 + 10 * 100_000_000, 1_000_000_000 + 20 * 100_000_000
    window = [e.log_time_ns for e in reader.messages(["/odom"], start_ns=start, end_ns=end)]
    assert window[0] == start and window[-1] == end - 100_000_000 and len(window) == 10


def test_info(tiny_recording: Path) -> None:
    """The summary gives topics, schemas, counts, span and the slamreplay metadata."""
    info = RecordingReader(tiny_recording).info
    topics = info.logical_topics()
    assert topics["/odom"].schema_name == "foxglove.PoseInFrame" and topics["/odom"].message_count == 100
    assert topics["/landmarks/range_bearing"].schema_name == "slamreplay.RangeBearingScan"
    assert info.message_count == 100 + 100 + 20 + 1
    assert (info.start_ns, info.end_ns) == (1_000_000_000, 1_000_000_000 + 99 * 100_000_000)
    assert info.metadata["slamreplay.recording"]["source"] == '{"test": "tiny"}'


def test_ros2_bag_directory_auto_mapped(tmp_path: Path) -> None:
    """A ROS 2 bag: Odometry -> /odom, PoseStamped -> /ground_truth/pose, Image -> /camera/image."""
    bag = write_ros2_bag(tmp_path / "bag")
    reader = RecordingReader(bag)
    assert reader.topic_map == {"/wheel/odom": "/odom", "/mocap/pose": "/ground_truth/pose",
                                "/camera/color": "/camera/image"}
    envs = list(reader.messages())
    odom = [e.msg for e in envs if e.topic == "/odom"]
    gt = [e.msg for e in envs if e.topic == "/ground_truth/pose"]
    imgs = [e.msg for e in envs if e.topic == "/camera/image"]
    assert len(odom) == len(gt) == len(imgs) == 20
    assert isinstance(odom[5], OdometryPose)
    assert odom[5].x_m == pytest.approx(0.55) and odom[5].yaw_rad == pytest.approx(0.25)
    assert isinstance(gt[5], GroundTruthPose) and gt[5].stamp_ns == 2_500_000_000
    assert isinstance(imgs[7], CameraImage) and imgs[7].encoding == "rgb8"
    assert np.all(imgs[7].pixels[..., 2] == 7) and np.all(imgs[7].pixels[..., 0] == 0)  # bgr8 -> rgb8


def test_ros2_explicit_topic_map(tmp_path: Path) -> None:
    """An explicit map wins over the automatic one, and an unknown source topic is an error."""
    bag = write_ros2_bag(tmp_path / "bag")
    reader = RecordingReader(bag, {"/mocap/pose": "/odom"})
    assert reader.topic_map["/mocap/pose"] == "/odom" and "/wheel/odom" not in reader.topic_map
    with pytest.raises(ReplayError, match="topic map names /nope, which is not in the recording"):
        RecordingReader(bag, {"/nope": "/odom"})
    with pytest.raises(ReplayError, match="not a slamreplay topic"):
        RecordingReader(bag, {"/mocap/pose": "/whatever"})


def test_bad_files(tmp_path: Path, tiny_recording: Path) -> None:
    """Missing, empty, not-MCAP, truncated files and sqlite bags each get a clear error."""
    with pytest.raises(ReplayError, match="no such file"):
        RecordingReader(tmp_path / "missing.mcap")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(ReplayError, match="is empty"):
        RecordingReader(empty)
    text = tmp_path / "notes.mcap"
    text.write_text("hello")
    with pytest.raises(ReplayError, match="not an MCAP file"):
        RecordingReader(text)
    data = tiny_recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ReplayError, match=r"truncated.*slamreplay recover"):
        RecordingReader(cut)
    sqlite_bag = tmp_path / "old_bag"
    sqlite_bag.mkdir()
    (sqlite_bag / "old_bag_0.db3").write_bytes(b"SQLite format 3")
    with pytest.raises(ReplayError, match="sqlite3 storage"):
        RecordingReader(sqlite_bag)


def test_crc_mismatch_is_reported(tmp_path: Path) -> None:
    """A corrupted chunk is reported as damage with the recover hint, not decoded silently."""
    path = tmp_path / "r.mcap"
    with Recorder(path, source={}) as rec:
        for k in range(2000):
            rec.write("/odom", OdometryPose(k + 1, k, 0, 0))
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[0]
    data = bytearray(path.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 50] ^= 0x01
    path.write_bytes(bytes(data))
    reader = RecordingReader(path)
    with pytest.raises(ReplayError, match=r"(corrupt|damaged).*slamreplay recover"):
        list(reader.messages())


def test_nan_and_missing_topic(tmp_path: Path) -> None:
    """A NaN written by another tool, and asking for a topic the file lacks."""
    path = tmp_path / "nan.mcap"
    from slamreplay.recorder.codec.schemas import RangeBearingScanProto

    good = RangeBearingScan(1, [1.0], [0.0], [1])
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(codec.schema_name(good), "protobuf", codec.schema_data(good))
        cid = w.register_channel("/landmarks/range_bearing", "protobuf", sid)
        bad = RangeBearingScanProto(ranges=[float("nan")], bearings=[0.0], landmark_ids=[1])
        w.add_message(cid, 5, bad.SerializeToString(), 5)
        w.finish()
    reader = RecordingReader(path)
    with pytest.raises(ReplayError, match=r"/landmarks/range_bearing message at log_time 5 ns is invalid.*NaN"):
        list(reader.messages())
    with pytest.raises(ReplayError, match=r"has no /odom topic.*--topic-map"):
        list(reader.messages(["/odom"]))


def test_channel_without_its_schema_is_damage(tmp_path: Path) -> None:
    """A channel whose schema record is missing is reported as damage, with the recover pointer."""
    path = tmp_path / "lost-schema.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel("/odom", "protobuf", 7)
        w.add_message(cid, 5, codec.encode(OdometryPose(5, 0.0, 0.0, 0.0)), 5)
        w.finish()
    reader = RecordingReader(path)
    with pytest.raises(ReplayError, match=r"is damaged \(topic /odom\): the Channel record of /odom refers to "
                                          r"schema 7, which no Schema record defines\. .*slamreplay recover"):
        reader.decoder("/odom")


@pytest.mark.parametrize(("at", "value", "match"), [
    ("footer", 10**9, r"the Footer puts the summary section at byte 1000000000, outside the file's data"),
    ("first", 2**40, r"Header record at byte 8 claims 1,099,511,627,776 bytes but only"),
])
def test_lengths_from_the_file_are_checked(tmp_path: Path, at: str, value: int, match: str) -> None:
    """A summary offset or record length past the end of the file is reported with the record and its offset."""
    import struct

    src = tmp_path / "ok.mcap"
    with Recorder(src, source={}) as rec:
        rec.write("/odom", OdometryPose(5, 0.0, 0.0, 0.0))
    data = bytearray(src.read_bytes())
    if at == "footer":
        struct.pack_into("<Q", data, len(data) - 8 - 20, value)  # Footer.summary_start
    else:
        struct.pack_into("<Q", data, 9, value)  # the Header record's length
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(ReplayError, match=match + r".*slamreplay recover"):
        RecordingReader(bad)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_order_across_overlapping_small_chunks(tmp_path: Path, seed: int) -> None:
    """Chunks that overlap in time (merged) and chunks that do not (yielded whole) give one order:
    log_time, then position in the file, with ties across chunk boundaries."""
    rng = np.random.default_rng(seed)
    times = np.sort(rng.integers(1, 400, 300))
    times[rng.choice(300, 60, replace=False)] = rng.integers(1, 400, 60)  # some out of order: chunks overlap
    pose = OdometryPose(1, 0.0, 0.0, 0.0)
    path = tmp_path / "r.mcap"
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=400)  # a few messages per chunk
        w.start()
        sid = w.register_schema(codec.schema_name(pose), "protobuf", codec.schema_data(pose))
        cid = w.register_channel("/odom", "protobuf", sid)
        for k, t in enumerate(times.tolist()):
            w.add_message(cid, log_time=t, publish_time=t, data=codec.encode(OdometryPose(t, float(k), 0.0, 0.0)),
                          sequence=k)
        w.finish()
    reader = RecordingReader(path)
    assert reader.info.chunk_count > 20
    got = [int(e.msg.x_m) for e in reader.messages()]  # type: ignore[union-attr]
    assert got == sorted(range(len(times)), key=lambda k: times[k])  # stable: ties keep write order
    window = [int(e.msg.x_m) for e in reader.messages(start_ns=100, end_ns=300)]  # type: ignore[union-attr]
    assert window == [k for k in got if 100 <= times[k] < 300]


def test_a_missing_topic_error_stays_one_short_line(tmp_path: Path) -> None:
    """A file of 65,535 channels (the format's most) without /odom: the error names the first 20 topics and how
    many more, not all of them (it was a 600 KB line)."""
    path = tmp_path / "many.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        for i in range(65_535):
            w.register_channel(topic=f"/t{i:05d}", message_encoding="json", schema_id=sid)
        w.finish()
    with pytest.raises(ReplayError) as err:
        RecordingReader(path).decoder("/odom")
    text = str(err.value)
    assert "/t00000, /t00001" in text and "/t00019 and 65,515 more (`slamreplay inspect` lists them)" in text
    assert "/t00020" not in text and len(text) < 600 and "\n" not in text
    with pytest.raises(ReplayError, match=r"topic map names /nope, .* and 65,515 more"):
        RecordingReader(path, {"/nope": "/odom"})
