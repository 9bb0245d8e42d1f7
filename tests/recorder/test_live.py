"""`record live`: a Foxglove SDK server (tests/recorder/live_peer.py, a subprocess) recorded over WebSocket."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from live_ros2_sim import messages_by_topic, sim_as_ros2_bag
from mcap.reader import make_reader
from patience import deadline as give_up_at

from slamreplay.api.cli.command import main as cli_main
from slamreplay.recorder.importers.foxglove_live import GAP_METADATA, LIVE_METADATA, LiveOptions, LiveRecording
from slamreplay.recorder.importers.ros2bag import import_ros2_bag
from slamreplay.recorder.messages import TOPIC_RANGE_BEARING, assert_msg_equal
from slamreplay.recorder.recover import recover
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
from slamreplay.recorder.sim.ros2bag import write_bag
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.runs.diff import metric_tolerance

pytest.importorskip("foxglove", reason="the Foxglove SDK (foxglove-sdk, in the dev extra) serves the test stream")
PEER = Path(__file__).with_name("live_peer.py")
REPO = Path(__file__).resolve().parents[2]


class Peer:
    """A live_peer.py subprocess: its URL once it listens, and the counts it sent once it is done."""

    def __init__(self, tmp: Path, mcap: Path, *args: str) -> None:
        self.port_file, self.sent_file = tmp / "peer.port", tmp / "peer.sent"
        self.proc = subprocess.Popen([sys.executable, str(PEER), str(mcap), "--port-file", str(self.port_file),
                                      "--sent-file", str(self.sent_file), *args], stderr=subprocess.PIPE, text=True)
        deadline = give_up_at(20)
        while not self.port_file.exists():
            assert self.proc.poll() is None, self.proc.stderr.read() if self.proc.stderr else ""
            assert time.monotonic() < deadline, "the peer did not start"
            time.sleep(0.02)
        self.url = f"ws://127.0.0.1:{self.port_file.read_text()}"

    def sent(self, timeout_s: float = 30) -> dict[str, int]:
        deadline = give_up_at(timeout_s)
        while not self.sent_file.exists():
            assert self.proc.poll() is None, self.proc.stderr.read() if self.proc.stderr else ""
            assert time.monotonic() < deadline, "the peer did not finish publishing"
            time.sleep(0.02)
        counts: dict[str, int] = json.loads(self.sent_file.read_text())
        return counts

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def peers(tmp_path: Path) -> Iterator[list[Peer]]:
    made: list[Peer] = []
    yield made
    for p in made:
        p.close()


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 30 s sim-landmarks recording (301 odometry and ground-truth poses, 151 scans, the landmark map)."""
    path = tmp_path_factory.mktemp("live") / "sim.mcap"
    simulate_landmarks(path, LandmarkSimConfig(duration_s=30.0), seed=3)
    return path


def _model(path: Path) -> SensorModel:
    with open(path, "rb") as f:
        record = next(m for m in make_reader(f).iter_metadata() if m.name == "slamreplay.recording")
    model = SensorModel.from_record(record.metadata)
    assert model is not None
    return model


def _record_all(peer: Peer, out: Path, **options: object) -> tuple[LiveRecording, list[str], object]:
    """Record until every message the peer sent on a recorded channel arrived; the recording, its lines, summary."""
    lines: list[str] = []
    live = LiveRecording(LiveOptions(url=peer.url, out=out, **options), say=lines.append)  # type: ignore[arg-type]
    done: dict[str, object] = {}
    thread = threading.Thread(target=lambda: done.setdefault("summary", live.run()))
    thread.start()
    try:
        sent = peer.sent()
        deadline = give_up_at(30)
        while time.monotonic() < deadline:
            got = {c.topic: c.received for c in live.status().topics}
            if got and all(got[t] >= sent.get(t, 0) for t in got):
                break
            time.sleep(0.02)
    finally:
        live.stop()
        thread.join(30)
    return live, lines, done["summary"]


def _sequence(path: Path) -> list[tuple[str, int]]:
    return [(e.topic, e.log_time_ns) for e in RecordingReader(path).messages()]


@pytest.fixture(scope="module")
def live_sim(sim: Path, tmp_path_factory: pytest.TempPathFactory
             ) -> Iterator[tuple[Path, list[str], Any, dict[str, int]]]:
    """``sim`` served by the peer and recorded live: the recording, the lines said, the summary, the counts sent."""
    tmp = tmp_path_factory.mktemp("live-sim")
    peer = Peer(tmp, sim, "--speed", "10")  # in real time at 10x: 30 s of simulation in 3 s
    try:
        _, lines, summary = _record_all(peer, tmp / "live.mcap", sensor_model=_model(sim))
        yield tmp / "live.mcap", lines, summary, peer.sent()
    finally:
        peer.close()


def test_live_protobuf_stream_records_every_message_as_the_direct_recording(
        sim: Path, live_sim: tuple[Path, list[str], Any, dict[str, int]]) -> None:
    """Foxglove protobuf channels come out as the simulation wrote them: every message the server sent, in order,
    byte for byte."""
    out, lines, summary, sent = live_sim
    assert out.exists() and not Path(f"{out}.partial").exists()
    assert {c.topic: c.written for c in summary.topics} == sent
    assert _sequence(out) == _sequence(sim)
    topics = sorted(sent)
    for a, b in zip(RecordingReader(sim).raw(topics), RecordingReader(out).raw(topics), strict=True):
        assert (a[0].topic, a[1], a[3]) == (b[0].topic, b[1], b[3])  # log time and bytes (publish time: received)
    for a, b in zip(RecordingReader(sim).messages(), RecordingReader(out).messages(), strict=True):
        assert_msg_equal(a.msg, b.msg)
    assert any("/diagnostics" in line and "skipped: schema my_robot.Diagnostics" in line for line in lines)
    with open(out, "rb") as f:
        live_meta = next(m.metadata for m in make_reader(f).iter_metadata() if m.name == LIVE_METADATA)
    assert json.loads(live_meta["topics"])["/odom"]["written"] == sent["/odom"]
    assert "/diagnostics" in json.loads(live_meta["skipped"])


def _metrics(recording: Path, pipeline: str, run: Path) -> dict[str, float]:
    assert cli_main(["run", str(recording), "--pipeline", pipeline, "--out", str(run), "-q"]) == 0
    return {k: v["value"] for k, v in json.loads((run / "metrics.json").read_text())["metrics"].items()}


def test_live_recording_replays_through_odometry_as_the_direct_recording(
        sim: Path, live_sim: tuple[Path, list[str], Any, dict[str, int]], tmp_path: Path) -> None:
    """`slamreplay run FILE --pipeline odometry` gives the metrics of the simulation recorded directly."""
    assert _metrics(live_sim[0], "odometry", tmp_path / "a") == _metrics(sim, "odometry", tmp_path / "b")


@pytest.mark.slow
def test_live_recording_replays_through_dslam_as_the_direct_recording(
        sim: Path, live_sim: tuple[Path, list[str], Any, dict[str, int]], tmp_path: Path) -> None:
    """D-SLAM on the live recording gives the metrics of the simulation recorded directly (issue 42)."""
    assert _metrics(live_sim[0], "dslam", tmp_path / "a") == _metrics(sim, "dslam", tmp_path / "b")


@pytest.fixture(scope="module")
def live_ros2_sim(sim: Path, tmp_path_factory: pytest.TempPathFactory
                  ) -> Iterator[tuple[Path, Path, list[str], Any, dict[str, int], dict[str, int]]]:
    """``sim`` as a ROS 2 robot publishes it (CDR nav_msgs/Odometry, sensor_msgs/LaserScan, tf2_msgs/TFMessage on
    /tf and /tf_static, as foxglove_bridge serves them) at 10x, recorded live with ground truth composed from /tf
    in ``map``; and the same bag imported by `record ros2`: (direct, live, lines, summary, sent, in the bag)."""
    tmp = tmp_path_factory.mktemp("live-ros2-sim")
    in_bag = sim_as_ros2_bag(sim, tmp / "bag")
    direct = tmp / "direct.mcap"
    import_ros2_bag(tmp / "bag", direct, ground_truth_frame="map")
    peer = Peer(tmp, tmp / "bag" / "bag.mcap", "--speed", "10")
    try:
        _, lines, summary = _record_all(peer, tmp / "live.mcap", ground_truth_frame="map")
        yield direct, tmp / "live.mcap", lines, summary, peer.sent(), in_bag
    finally:
        peer.close()


def test_live_ros2_stream_of_the_simulation_loses_no_message(
        live_ros2_sim: tuple[Path, Path, list[str], Any, dict[str, int], dict[str, int]]) -> None:
    """Every message the ROS 2 server sent arrived (counted on both sides), and the recording holds what `record
    ros2` makes of the same messages: odometry, the scans' poles, ground truth composed through /tf."""
    direct, out, lines, summary, sent, in_bag = live_ros2_sim
    assert sent == in_bag  # the server sent the whole simulation, to the recorder
    assert {c.topic: c.received for c in summary.topics} == sent
    assert all(c.bad == 0 for c in summary.topics)
    assert any(line.strip().startswith("/tf ") and "-> transform tree (ground truth composed through the tree)"
               in line for line in lines), lines
    by_topic = messages_by_topic(direct)
    live = messages_by_topic(out)
    assert {t: len(m) for t, m in live.items()} == {t: len(m) for t, m in by_topic.items()} == {
        "/odom": 301, "/ground_truth/pose": 301, TOPIC_RANGE_BEARING: 151}
    for topic, msgs in by_topic.items():
        for a, b in zip(msgs, live[topic], strict=True):
            assert_msg_equal(a, b, atol=1e-9)


def _same_metrics(a: Path, b: Path) -> None:
    """The runs' metrics are the same within each metric's diff tolerance (what `slamreplay diff` calls same)."""
    ma = json.loads((a / "metrics.json").read_text())["metrics"]
    mb = json.loads((b / "metrics.json").read_text())["metrics"]
    assert sorted(ma) == sorted(mb)
    for name, entry in ma.items():
        va, vb = entry["value"], mb[name]["value"]
        assert abs(vb - va) <= metric_tolerance(entry, va), (name, va, vb)


@pytest.mark.slow
def test_live_ros2_recording_replays_through_dslam_as_record_ros2(
        live_ros2_sim: tuple[Path, Path, list[str], Any, dict[str, int], dict[str, int]], tmp_path: Path) -> None:
    """D-SLAM on the ROS 2 stream recorded live gives the metrics of the same simulation imported by `record ros2`
    (issue 42's ROS 2 done-means)."""
    direct, out = live_ros2_sim[:2]
    live_metrics, direct_metrics = _metrics(out, "dslam", tmp_path / "a"), _metrics(direct, "dslam", tmp_path / "b")
    _same_metrics(tmp_path / "a", tmp_path / "b")
    assert live_metrics["landmarks_mapped"] >= 10 and live_metrics["ape_rmse_m"] < 0.05, live_metrics
    assert live_metrics == direct_metrics


def test_live_ros2_cdr_channels_convert_as_record_ros2_does(tmp_path: Path, peers: list[Peer]) -> None:
    """CDR channels (odometry, IMU, laser scans, camera, tf_static) become what `record ros2` makes of the same bag."""
    bag = tmp_path / "bag"
    write_bag(bag, "mcap", seed=0, seconds=6.0)
    imported = tmp_path / "imported.mcap"
    import_ros2_bag(bag, imported)
    peers.append(peer := Peer(tmp_path, bag / "bag.mcap"))
    out = tmp_path / "live.mcap"
    _, _, summary = _record_all(peer, out)
    by_topic = messages_by_topic(imported)
    live = messages_by_topic(out)
    assert sorted(live) == sorted(by_topic) and TOPIC_RANGE_BEARING in live
    for topic, msgs in by_topic.items():
        assert len(live[topic]) == len(msgs), topic
        for a, b in zip(msgs, live[topic], strict=True):
            assert_msg_equal(a, b)  # type: ignore[arg-type]
    skipped = {p.channel.topic: p.note for p in summary.skipped}  # type: ignore[attr-defined]
    assert "my_msgs/msg/Blob is not read" in skipped["/diagnostics_blob"]
    assert "/camera/image comes from /camera/compressed" in skipped["/camera/image_raw"]
    assert _model(out) == _model(imported)  # the pole extractor's noise floors, as the import states them


def test_live_odometry_only_on_tf_is_composed_as_record_ros2_does(tmp_path: Path, peers: list[Peer]) -> None:
    """A robot without nav_msgs/Odometry: /odom is base_link in odom through /tf (and /tf_static), pose for pose as
    `record ros2` composes it, and ground truth is base_link in map."""
    bag = tmp_path / "bag"
    write_bag(bag, "mcap", seed=1, seconds=4.0, skip=("/odom", "/camera/image_raw", "/camera/compressed",
                                                       "/camera/camera_info", "/diagnostics_blob"))
    imported = tmp_path / "imported.mcap"
    import_ros2_bag(bag, imported, ground_truth_frame="map")
    peers.append(peer := Peer(tmp_path, bag / "bag.mcap"))
    out = tmp_path / "live.mcap"
    _, lines, summary = _record_all(peer, out, ground_truth_frame="map")
    assert any("odometry and ground truth composed through the tree" in line for line in lines), lines
    want = messages_by_topic(imported)
    got = messages_by_topic(out)
    assert sorted(got) == sorted(want) == sorted(["/ground_truth/pose", "/imu/yaw_rate", "/odom", TOPIC_RANGE_BEARING])
    assert len(got["/odom"]) == len(want["/odom"]) == 40
    for topic in ("/odom", "/ground_truth/pose"):
        for a, b in zip(want[topic], got[topic], strict=True):
            assert_msg_equal(a, b, atol=1e-9)
    tf = next(c for c in summary.topics if c.topic == "/tf")  # type: ignore[attr-defined]
    assert tf.written == 80  # the poses composed through it


def test_live_frame_options_reach_the_recording() -> None:
    """--base-frame, --odom-frame and --ground-truth-frame choose the frames /tf is composed between."""
    from slamreplay.api.cli.command import build_parser
    from slamreplay.api.cli.live_cli import live_options

    args = build_parser().parse_args(["record", "live", "ws://robot:8765", "--out", "x.mcap", "--base-frame",
                                      "chassis", "--odom-frame", "wheel_odom", "--ground-truth-frame", "map"])
    o = live_options(args)
    assert (o.base_frame, o.odom_frame, o.ground_truth_frame) == ("chassis", "wheel_odom", "map")
    o = live_options(build_parser().parse_args(["record", "live", "ws://robot:8765", "--out", "x.mcap"]))
    assert (o.base_frame, o.odom_frame, o.ground_truth_frame) == ("base_link", "odom", None)


def test_live_kill9_leaves_a_partial_that_recover_salvages(sim: Path, tmp_path: Path, peers: list[Peer]) -> None:
    """kill -9 of `slamreplay record live` mid-way: FILE.partial, and `recover` keeps every message flushed."""
    peers.append(peer := Peer(tmp_path, sim, "--speed", "10"))  # 30 s of simulation in 3 s
    out = tmp_path / "live.mcap"
    env = {**os.environ, "SLAMREPLAY_PROGRESS_INTERVAL_S": "0"}
    proc = subprocess.Popen([sys.executable, "-m", "slamreplay.api.cli", "record", "live", peer.url, "--out", str(out)],
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    assert proc.stderr is not None
    flushed = 0
    watchdog = threading.Timer(60, proc.kill)  # a recorder that hangs ends the test, not the suite
    watchdog.start()
    try:
        for line in proc.stderr:  # a status line comes after each flush: what it counts is on disk
            if line.startswith("record live") and " messages" in line:
                flushed = int(line.split(", ")[1].split()[0].replace(",", ""))
                if flushed >= 300:
                    break
    finally:
        watchdog.cancel()
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    partial = Path(f"{out}.partial")
    assert partial.exists() and not out.exists()
    report = recover(partial, tmp_path / "fixed.mcap")
    assert report.messages >= flushed >= 300
    got = _sequence(tmp_path / "fixed.mcap")
    assert got == _sequence(sim)[:len(got)]  # a prefix of what was sent, nothing damaged


def test_live_ctrl_c_ends_the_recording_cleanly(sim: Path, tmp_path: Path, peers: list[Peer]) -> None:
    """Ctrl-C (SIGINT) is the normal end: exit 0, FILE (no .partial), what came so far, the summary line."""
    peers.append(peer := Peer(tmp_path, sim, "--speed", "10"))
    out = tmp_path / "live.mcap"
    env = {**os.environ, "SLAMREPLAY_PROGRESS_INTERVAL_S": "0"}
    proc = subprocess.Popen([sys.executable, "-m", "slamreplay.api.cli", "record", "live", peer.url, "--out", str(out)],
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    assert proc.stderr is not None
    watchdog = threading.Timer(60, proc.kill)  # a recorder that hangs ends the test, not the suite
    watchdog.start()
    try:
        for line in proc.stderr:
            if line.startswith("record live") and " messages" in line:
                break
        proc.send_signal(signal.SIGINT)
        _, rest = proc.communicate(timeout=30)
    finally:
        watchdog.cancel()
        proc.kill()
    assert proc.wait() == 0, rest
    assert out.exists() and not Path(f"{out}.partial").exists()
    got = _sequence(out)
    assert got and got == _sequence(sim)[:len(got)]
    assert "stopping: finishing the recording" in rest and f"wrote {out}: {len(got):,} messages" in rest


def test_live_dropped_connection_is_one_gap_in_the_file_and_said(sim: Path, tmp_path: Path,
                                                                  peers: list[Peer]) -> None:
    """The server goes away for 5 s (issue 42): the recording goes on after it, with one gap record written and
    said, and every message sent before and after it."""
    peers.append(peer := Peer(tmp_path, sim, "--drop-after", "400", "--drop-for", "5"))
    out = tmp_path / "live.mcap"
    _, lines, summary = _record_all(peer, out, sensor_model=_model(sim))
    assert {c.topic: c.written for c in summary.topics} == peer.sent()  # type: ignore[attr-defined]
    assert _sequence(out) == _sequence(sim)
    with open(out, "rb") as f:
        gaps = [m.metadata for m in make_reader(f).iter_metadata() if m.name == GAP_METADATA]
    assert len(gaps) == 1 and len(summary.gaps) == 1  # type: ignore[attr-defined]
    gap = gaps[0]
    assert 5.0 < float(gap["duration_s"]) < 5.0 + 10 * (give_up_at(1) - time.monotonic())
    assert 0 < int(gap["start_ns"]) <= int(gap["end_ns"])  # the log times of the messages around it
    stamps = [t for _, t in _sequence(out)]
    # 400 messages before the gap, the rest after it (messages of one stamp may lie on both sides)
    assert sum(t <= int(gap["start_ns"]) for t in stamps) >= 400
    assert sum(t >= int(gap["end_ns"]) for t in stamps) >= len(stamps) - 400 > 300
    assert sum(line.startswith("connection lost") for line in lines) == 1
    said = [line for line in lines if line.startswith("gap: ")]
    assert len(said) == 1 and said[0].startswith(f"gap: {float(gap['duration_s']):.1f} s without a connection"), said


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(("url", "extra", "expected"), [
    ("http://127.0.0.1:8765", [], r"is not a WebSocket URL: give ws://HOST:PORT"),
    ("ws://", [], r"is not a WebSocket URL"),
    ("ws://127.0.0.1:{free}", [], r"cannot connect to ws://127\.0\.0\.1:\d+: .*is foxglove_bridge"),
])
def test_live_bad_url_or_unreachable_server_exits_2_with_one_line(
        url: str, extra: list[str], expected: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A URL that is not ws:// or a server that is not there: exit 2, one line, no file."""
    out = tmp_path / "live.mcap"
    code = cli_main(["record", "live", url.format(free=_free_port()), "--out", str(out), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    import re

    assert re.search(expected, err[0]), err[0]
    assert not out.exists() and not Path(f"{out}.partial").exists()


def test_live_no_matching_topic_exits_2_naming_the_channels(sim: Path, tmp_path: Path, peers: list[Peer],
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """--topics that match nothing, or only a channel slamreplay cannot read: exit 2, one line naming the channels."""
    peers.append(peer := Peer(tmp_path, sim, "--linger-s", "60"))
    out = tmp_path / "live.mcap"
    assert cli_main(["record", "live", peer.url, "--out", str(out), "--topics", "/nothing/*", "--wait-s", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no channel of ws://" in err[0] and "matches --topics /nothing/*" in err[0]
    assert "/odom (protobuf foxglove.PoseInFrame)" in err[0]
    assert cli_main(["record", "live", peer.url, "--out", str(out), "--topics", "re:/diag.*", "--wait-s", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "can be recorded" in err[0]
    assert "my_robot.Diagnostics is not one slamreplay reads" in err[0]
    assert not out.exists() and not Path(f"{out}.partial").exists()
