"""Codec round trips: every message type survives encode -> MCAP schema -> decode."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from mcap.records import Schema

from slamreplay.recorder import codec
from slamreplay.recorder.errors import CodecError
from slamreplay.recorder.messages import (
    CameraCalibration,
    CameraImage,
    GroundTruthPose,
    ImuYawRate,
    LandmarkMap,
    Message,
    OdometryPose,
    RangeBearingScan,
    assert_msg_equal,
)

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
stamps = st.integers(min_value=1, max_value=2**62)


def roundtrip(msg: Message, topic: str = "/t") -> Message:
    """Encode with the message's schema, then decode through a TopicDecoder."""
    schema = Schema(id=1, name=codec.schema_name(msg), encoding="protobuf", data=codec.schema_data(msg))
    return codec.TopicDecoder(topic, type(msg), schema, "protobuf")(codec.encode(msg), msg.stamp_ns)


@given(stamps, finite, finite, st.floats(min_value=-math.pi + 1e-9, max_value=math.pi - 1e-9))
def test_planar_pose_roundtrip(stamp: int, x: float, y: float, yaw: float) -> None:
    """Odometry and ground-truth poses keep position exactly and heading to 1e-12 rad."""
    for cls in (OdometryPose, GroundTruthPose):
        msg = cls(stamp, x, y, yaw)
        back = roundtrip(msg)
        assert isinstance(back, cls)
        assert (back.stamp_ns, back.x_m, back.y_m) == (stamp, x, y)
        assert abs(math.remainder(back.yaw_rad - yaw, 2 * math.pi)) < 1e-12


@given(stamps, st.integers(0, 20).flatmap(lambda n: st.tuples(
    arrays(np.float64, n, elements=st.floats(0, 100)), arrays(np.float64, n, elements=st.floats(-4, 4)),
    arrays(np.int64, n, elements=st.integers(-1, 10**9)))), st.floats(0, 1), st.floats(0, 1))
def test_range_bearing_roundtrip(stamp: int, arrs: tuple[np.ndarray, ...], rs: float, bs: float) -> None:
    """Scans keep ranges, bearings, ids (with -1 unknown) and sigmas exactly."""
    msg = RangeBearingScan(stamp, *arrs, range_sigma_m=rs, bearing_sigma_rad=bs)
    assert_msg_equal(roundtrip(msg), msg)


@given(stamps, finite, st.floats(0, 10))
def test_imu_yaw_rate_roundtrip(stamp: int, rate: float, sigma: float) -> None:
    """Gyro yaw rates keep rate and sigma exactly; a negative sigma is refused."""
    msg = ImuYawRate(stamp, rate, sigma)
    back = roundtrip(msg)
    assert isinstance(back, ImuYawRate) and (back.yaw_rate_radps, back.yaw_rate_sigma_radps) == (rate, sigma)
    with pytest.raises(ValueError, match="yaw_rate_sigma_radps"):
        ImuYawRate(stamp, rate, -1.0)


@given(stamps, st.integers(0, 30).flatmap(lambda n: arrays(np.float64, (n, 2), elements=finite)))
def test_landmark_map_roundtrip(stamp: int, positions: np.ndarray) -> None:
    """Landmark maps keep ids and positions exactly."""
    msg = LandmarkMap(stamp, np.arange(len(positions)) * 7, positions)
    assert_msg_equal(roundtrip(msg), msg)


@settings(max_examples=25)
@given(stamps, st.sampled_from(["raw", "png"]), st.booleans(),
       st.tuples(st.integers(1, 12), st.integers(1, 12)), st.integers(0, 2**32 - 1))
def test_lossless_image_roundtrip(stamp: int, compression: str, rgb: bool, hw: tuple[int, int], seed: int) -> None:
    """Raw and PNG images come back pixel for pixel, mono8 and rgb8."""
    shape = (*hw, 3) if rgb else hw
    pixels = np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
    msg = CameraImage(stamp, pixels, "cam", compression)  # type: ignore[arg-type]
    back = roundtrip(msg)
    assert_msg_equal(back, msg)


def test_jpeg_image_is_close() -> None:
    """JPEG is lossy: a smooth image comes back within a few grey levels."""
    yy, xx = np.mgrid[0:64, 0:64]
    pixels = (2 * xx + yy).astype(np.uint8)
    back = roundtrip(CameraImage(5, pixels, compression="jpeg"))
    assert isinstance(back, CameraImage) and back.compression == "jpeg"
    assert np.abs(back.pixels.astype(int) - pixels).mean() < 2.0


def test_calibration_roundtrip() -> None:
    """Camera calibration keeps K, D and the model."""
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    msg = CameraCalibration(9, 320, 240, K, np.array([0.1, -0.01, 0, 0, 0]))
    assert_msg_equal(roundtrip(msg), msg)


def test_decoder_refuses_wrong_schema() -> None:
    """A topic whose schema cannot give the expected type is refused up front, naming both."""
    msg = OdometryPose(1, 0, 0, 0)
    schema = Schema(id=1, name=codec.schema_name(msg), encoding="protobuf", data=codec.schema_data(msg))
    with pytest.raises(CodecError, match=r"/scan has schema foxglove.PoseInFrame.*RangeBearingScan"):
        codec.TopicDecoder("/scan", RangeBearingScan, schema, "protobuf")


def test_decoder_refuses_unknown_encoding() -> None:
    """JSON channels are not read: the error names the encodings that are."""
    schema = Schema(id=1, name="foxglove.PoseInFrame", encoding="jsonschema", data=b"{}")
    with pytest.raises(CodecError, match="not supported"):
        codec.TopicDecoder("/odom", OdometryPose, schema, "json")


def test_decoder_reports_nan_and_garbage() -> None:
    """A NaN or undecodable payload raises CodecError naming the topic and log time."""
    msg = RangeBearingScan(1, [1.0], [0.0], [3])
    schema = Schema(id=1, name=codec.schema_name(msg), encoding="protobuf", data=codec.schema_data(msg))
    dec = codec.TopicDecoder("/landmarks/range_bearing", RangeBearingScan, schema, "protobuf")
    from slamreplay.recorder.codec.schemas import RangeBearingScanProto

    bad = RangeBearingScanProto(ranges=[float("nan")], bearings=[0.0], landmark_ids=[1]).SerializeToString()
    with pytest.raises(CodecError, match=r"/landmarks/range_bearing message at log_time 42 ns.*NaN"):
        dec(bad, 42)
    with pytest.raises(CodecError, match="log_time 43"):
        dec(b"\xff\xff\xff", 43)


def test_implausible_decoded_values_are_damage() -> None:
    """A pose a billion metres out, or a range beyond it, decodes to CodecError: damaged bytes, not a place."""
    from slamreplay.recorder.codec import TopicDecoder

    pose = OdometryPose(5, 2e9, 0.0, 0.0)
    schema = Schema(id=1, name=codec.schema_name(pose), encoding="protobuf", data=codec.schema_data(pose))
    dec = TopicDecoder("/odom", OdometryPose, schema, "protobuf")
    with pytest.raises(CodecError, match=r"/odom message at log_time 5 ns is invalid .*x_m holds 2e\+09 m, beyond any"):
        dec(codec.encode(pose), 5)
    assert dec(codec.encode(OdometryPose(5, 9e8, -9e8, 1.0)), 5).x_m == 9e8
    scan = RangeBearingScan(5, np.array([1.0, 3e9]), np.array([0.0, 0.1]), np.array([-1, -1]), 0.1, 0.01)
    schema = Schema(id=2, name=codec.schema_name(scan), encoding="protobuf", data=codec.schema_data(scan))
    with pytest.raises(CodecError, match=r"ranges_m holds 3e\+09 m"):
        TopicDecoder("/landmarks/range_bearing", RangeBearingScan, schema, "protobuf")(codec.encode(scan), 5)


def _schema(name: str, encoding: str, data: bytes) -> Schema:
    return Schema(id=1, name=name, encoding=encoding, data=data)


def test_damaged_schema_is_codec_error() -> None:
    """A FileDescriptorSet that is not protobuf, or whose files do not build, is a CodecError naming the topic."""
    from slamreplay.recorder.codec import TopicDecoder

    pose = OdometryPose(5, 0.0, 0.0, 0.0)
    with pytest.raises(CodecError, match=r"topic /odom: its schema foxglove.PoseInFrame \(protobuf, 4 bytes\) is "
                                         r"damaged and cannot be parsed: DecodeError"):
        TopicDecoder("/odom", OdometryPose, _schema("foxglove.PoseInFrame", "protobuf", b"\xff" * 4), "protobuf")
    data = codec.schema_data(pose).replace(b"foxglove/Vector3.proto", b"foxglove/Vector4.proto", 1)
    with pytest.raises(CodecError, match=r"is damaged and cannot be parsed: TypeError: Couldn't build proto file"):
        TopicDecoder("/odom", OdometryPose, _schema("foxglove.PoseInFrame", "protobuf", data), "protobuf")
    with pytest.raises(CodecError, match=r"\(ros2msg, 3 bytes\) is damaged and cannot be parsed: UnicodeDecodeError"):
        TopicDecoder("/odom", OdometryPose, _schema("nav_msgs/msg/Odometry", "ros2msg", b"\xff\xfe\xfd"), "cdr")
