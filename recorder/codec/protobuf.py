"""Messages <-> protobuf: Foxglove well-known schemas and slamreplay's custom ones.

| message            | schema                                             |
| ------------------ | -------------------------------------------------- |
| OdometryPose       | foxglove.PoseInFrame (frame ``odom``)              |
| GroundTruthPose    | foxglove.PoseInFrame (frame ``world``)             |
| RangeBearingScan   | slamreplay.RangeBearingScan                        |
| LandmarkMap        | slamreplay.LandmarkMap (frame ``world``)           |
| CameraImage        | foxglove.CompressedImage (png/jpeg) or RawImage   |
| CameraCalibration  | foxglove.CameraCalibration                         |
| VelocityCommand    | slamreplay.VelocityCommand                         |
| NavLocalization    | slamreplay.NavLocalization (frame ``map``)         |
| ImuYawRate         | slamreplay.ImuYawRate (frame ``base_link``)        |

Planar poses are stored in 3D with z = 0 and the heading as a quaternion about +z.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Callable
from functools import cache
from typing import Any, Literal, cast

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration as CameraCalibrationProto
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage as CompressedImageProto
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame as PoseInFrameProto
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage as RawImageProto
from mcap_protobuf.schema import build_file_descriptor_set

from slamreplay.recorder.codec.bounds import MAX_IMAGE_PIXELS, MAX_PNG_CHUNKS, check_image_size
from slamreplay.recorder.codec.schemas import (
    ImuYawRateProto,
    LandmarkMapProto,
    NavLocalizationProto,
    RangeBearingScanProto,
    VelocityCommandProto,
)
from slamreplay.recorder.errors import CodecError
from slamreplay.recorder.messages import (
    CameraCalibration,
    CameraImage,
    GroundTruthPose,
    ImuYawRate,
    LandmarkMap,
    Message,
    NavLocalization,
    OdometryPose,
    PlanarPose,
    RangeBearingScan,
    VelocityCommand,
)

PNG_LEVEL = 1  # fast; PNG is lossless at every level


def _proto_class(msg: Message) -> Any:
    if isinstance(msg, PlanarPose):
        return PoseInFrameProto
    if isinstance(msg, RangeBearingScan):
        return RangeBearingScanProto
    if isinstance(msg, LandmarkMap):
        return LandmarkMapProto
    if isinstance(msg, CameraImage):
        return RawImageProto if msg.compression == "raw" else CompressedImageProto
    if isinstance(msg, CameraCalibration):
        return CameraCalibrationProto
    if isinstance(msg, VelocityCommand):
        return VelocityCommandProto
    if isinstance(msg, NavLocalization):
        return NavLocalizationProto
    if isinstance(msg, ImuYawRate):
        return ImuYawRateProto
    raise CodecError(f"no schema for message type {type(msg).__name__}")


def schema_name(msg: Message) -> str:
    """The MCAP schema name a message is written with, e.g. ``foxglove.PoseInFrame``."""
    return str(_proto_class(msg).DESCRIPTOR.full_name)


@cache
def _schema_data(full_name: str) -> bytes:
    classes = (PoseInFrameProto, RangeBearingScanProto, LandmarkMapProto, RawImageProto,
               CompressedImageProto, CameraCalibrationProto, VelocityCommandProto, NavLocalizationProto,
               ImuYawRateProto)
    cls = next(c for c in classes if c.DESCRIPTOR.full_name == full_name)
    return bytes(build_file_descriptor_set(cls).SerializeToString())


def schema_data(msg: Message) -> bytes:
    """The serialized ``FileDescriptorSet`` for a message's schema (MCAP schema ``data``)."""
    return _schema_data(schema_name(msg))


def encode(msg: Message) -> bytes:
    """Serialize a message with its protobuf schema."""
    proto = _to_proto(msg)
    proto.timestamp.FromNanoseconds(msg.stamp_ns)
    return bytes(proto.SerializeToString())


def _to_proto(msg: Message) -> Any:
    if isinstance(msg, PlanarPose):
        half = 0.5 * msg.yaw_rad
        p = PoseInFrameProto(frame_id=type(msg).FRAME_ID)
        p.pose.position.x, p.pose.position.y, p.pose.position.z = msg.x_m, msg.y_m, 0.0
        o = p.pose.orientation
        o.w, o.x, o.y, o.z = math.cos(half), 0.0, 0.0, math.sin(half)
        return p
    if isinstance(msg, RangeBearingScan):
        return RangeBearingScanProto(
            frame_id="base_link", ranges=msg.ranges_m.tolist(), bearings=msg.bearings_rad.tolist(),
            landmark_ids=msg.landmark_ids.tolist(), range_sigma=msg.range_sigma_m,
            bearing_sigma=msg.bearing_sigma_rad,
        )
    if isinstance(msg, LandmarkMap):
        return LandmarkMapProto(
            frame_id="world", landmark_ids=msg.landmark_ids.tolist(),
            x=msg.positions_m[:, 0].tolist(), y=msg.positions_m[:, 1].tolist(),
        )
    if isinstance(msg, CameraImage):
        if msg.compression == "raw":
            channels = 1 if msg.encoding == "mono8" else 3
            return RawImageProto(
                frame_id=msg.frame_id, width=msg.width_px, height=msg.height_px, encoding=msg.encoding,
                step=msg.width_px * channels, data=np.ascontiguousarray(msg.pixels).tobytes(),
            )
        bgr = msg.pixels if msg.pixels.ndim == 2 else cv2.cvtColor(msg.pixels, cv2.COLOR_RGB2BGR)
        ext, params = (".png", [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL]) if msg.compression == "png" else (
            ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95])
        ok, buf = cv2.imencode(ext, bgr, params)
        if not ok:
            raise CodecError(f"could not encode a {msg.width_px}x{msg.height_px} image as {msg.compression}")
        return CompressedImageProto(frame_id=msg.frame_id, format=msg.compression, data=buf.tobytes())
    if isinstance(msg, CameraCalibration):
        K = msg.K
        P = np.hstack([K, np.zeros((3, 1))])
        return CameraCalibrationProto(
            frame_id=msg.frame_id, width=msg.width_px, height=msg.height_px,
            distortion_model=msg.distortion_model, D=msg.D.tolist(), K=K.ravel().tolist(),
            R=np.eye(3).ravel().tolist(), P=P.ravel().tolist(),
        )
    if isinstance(msg, VelocityCommand):
        return VelocityCommandProto(frame_id="base_link", linear=msg.linear_mps, angular=msg.angular_radps)
    if isinstance(msg, NavLocalization):
        return NavLocalizationProto(frame_id=NavLocalization.FRAME_ID, x=msg.x_m, y=msg.y_m, yaw=msg.yaw_rad,
                                    node=msg.node, x_translation=msg.x_translation_px,
                                    heading_deviation=msg.heading_deviation_rad, corrected=msg.corrected)
    if isinstance(msg, ImuYawRate):
        return ImuYawRateProto(frame_id=ImuYawRate.FRAME_ID, yaw_rate=msg.yaw_rate_radps,
                               yaw_rate_sigma=msg.yaw_rate_sigma_radps)
    raise CodecError(f"no schema for message type {type(msg).__name__}")


def yaw_from_quaternion(w: float, x: float, y: float, z: float) -> float:
    """Heading (rotation about +z) of a unit quaternion, in radians."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def stamp_of(proto: Any, log_time_ns: int) -> int:
    """The message's own timestamp in ns, or ``log_time_ns`` when the message carries none."""
    ts = proto.timestamp
    ns = int(ts.seconds) * 1_000_000_000 + int(ts.nanos)
    return ns if ns > 0 else log_time_ns


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png(data: bytes) -> None:
    """CodecError unless every chunk of a PNG is whole and passes its CRC.

    Checked before OpenCV sees the bytes: libpng reports damage on the process's stderr
    before it fails, which would break the one-line error a user gets.
    """
    pos, chunks = len(PNG_SIGNATURE), 0
    while pos < len(data):
        chunks += 1
        if chunks > MAX_PNG_CHUNKS:
            raise CodecError(f"PNG data holds more than {MAX_PNG_CHUNKS:,} chunks, above slamreplay's limit: the "
                             f"image is damaged or hostile")
        if pos + 12 > len(data):
            raise CodecError(f"PNG data is cut short at byte {pos} of {len(data)}")
        length, kind = struct.unpack_from(">I4s", data, pos)
        if pos + 12 + length > len(data):
            raise CodecError(f"PNG chunk {kind!r} at byte {pos} claims {length} bytes, past the end of the image")
        (crc,) = struct.unpack_from(">I", data, pos + 8 + length)
        if zlib.crc32(data[pos + 4:pos + 8 + length]) != crc:
            raise CodecError(f"PNG chunk {kind!r} at byte {pos} fails its CRC check: the image is damaged")
        pos += 12 + length
        if kind == b"IEND":
            return
    raise CodecError("PNG data has no IEND chunk: the image is cut short")


def decode_image_bytes(data: bytes, fmt: str) -> np.ndarray:
    """Decode PNG/JPEG bytes to mono8 (H, W) or rgb8 (H, W, 3) pixels."""
    if data.startswith(PNG_SIGNATURE):
        check_png(data)
    check_image_size(data, fmt)  # before OpenCV allocates the pixels the header claims
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise CodecError(f"image data is not a readable {fmt or 'PNG/JPEG'} file")
    if arr.dtype != np.uint8:
        raise CodecError(f"only 8-bit images are supported, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 4:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2RGB)
    elif arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)
    return arr


def raw_pixels(data: bytes, width: int, height: int, step: int, encoding: str) -> np.ndarray:
    """Pixels of a raw image buffer (foxglove.RawImage or sensor_msgs/Image) as mono8/rgb8."""
    channels = {"mono8": 1, "8UC1": 1, "rgb8": 3, "bgr8": 3, "8UC3": 3}.get(encoding)
    if channels is None:
        raise CodecError(f"image encoding {encoding!r} is not supported (use mono8, rgb8 or bgr8)")
    if width * height > MAX_IMAGE_PIXELS:
        raise CodecError(f"the raw image header claims {width:,} x {height:,} pixels; slamreplay decodes at most "
                         f"{MAX_IMAGE_PIXELS:,} pixels per image: the image is damaged or hostile")
    if width <= 0 or height <= 0 or step < width * channels or len(data) < step * height:
        raise CodecError(f"raw image buffer of {len(data)} bytes does not fit {width}x{height} step {step}")
    rows = np.frombuffer(data, np.uint8, count=step * height).reshape(height, step)
    px = rows[:, : width * channels].reshape(height, width, channels)
    if encoding == "bgr8":
        px = px[:, :, ::-1]
    return px[:, :, 0] if channels == 1 else px


def from_proto(kind: type, proto: Any, log_time_ns: int) -> Message:
    """Build a message of type ``kind`` from a decoded protobuf object.

    Raises ValueError (from the message model) for non-finite or inconsistent values and
    CodecError when the schema does not fit ``kind``.
    """
    name = proto.DESCRIPTOR.full_name
    stamp = stamp_of(proto, log_time_ns)
    if issubclass(kind, PlanarPose) and name == "foxglove.PoseInFrame":
        p, o = proto.pose.position, proto.pose.orientation
        # kind is an OdometryPose/GroundTruthPose subclass of PlanarPose in practice
        return cast(Message, kind(stamp, p.x, p.y, yaw_from_quaternion(o.w, o.x, o.y, o.z)))
    if kind is RangeBearingScan and name == "slamreplay.RangeBearingScan":
        return RangeBearingScan(stamp, np.array(proto.ranges), np.array(proto.bearings),
                                np.array(proto.landmark_ids, dtype=np.int64), proto.range_sigma, proto.bearing_sigma)
    if kind is LandmarkMap and name == "slamreplay.LandmarkMap":
        return LandmarkMap(stamp, np.array(proto.landmark_ids, dtype=np.int64),
                           np.stack([np.array(proto.x), np.array(proto.y)], -1).reshape(-1, 2))
    if kind is CameraImage and name == "foxglove.CompressedImage":
        fmt = proto.format.lower()
        compression: Literal["jpeg", "png"] = "jpeg" if "jp" in fmt else "png"
        return CameraImage(stamp, decode_image_bytes(proto.data, fmt), proto.frame_id or "camera", compression)
    if kind is CameraImage and name == "foxglove.RawImage":
        px = raw_pixels(proto.data, proto.width, proto.height, proto.step, proto.encoding)
        return CameraImage(stamp, px, proto.frame_id or "camera", "raw")
    if kind is CameraCalibration and name == "foxglove.CameraCalibration":
        return CameraCalibration(stamp, proto.width, proto.height, np.array(proto.K).reshape(3, 3),
                                 np.array(proto.D), proto.distortion_model or "plumb_bob", proto.frame_id or "camera")
    if kind is VelocityCommand and name == "slamreplay.VelocityCommand":
        return VelocityCommand(stamp, proto.linear, proto.angular)
    if kind is NavLocalization and name == "slamreplay.NavLocalization":
        return NavLocalization(stamp, proto.x, proto.y, proto.yaw, proto.node, proto.x_translation,
                               proto.heading_deviation, proto.corrected)
    if kind is ImuYawRate and name == "slamreplay.ImuYawRate":
        return ImuYawRate(stamp, proto.yaw_rate, proto.yaw_rate_sigma)
    raise CodecError(f"schema {name} cannot be read as {kind.__name__}")


def proto_converter(kind: type, schema_name: str) -> Callable[[Any, int], Message]:
    """``from_proto`` for one (message type, schema) pair, with the hot case (poses) specialised.

    A pose is decoded for most messages of a recording: its converter reads the fields
    directly instead of dispatching on the schema name for every message.
    """
    if issubclass(kind, PlanarPose) and schema_name == "foxglove.PoseInFrame":
        atan2 = math.atan2

        def pose(proto: Any, log_time_ns: int) -> Message:
            ts = proto.timestamp
            ns = ts.seconds * 1_000_000_000 + ts.nanos
            p, o = proto.pose.position, proto.pose.orientation
            w, x, y, z = o.w, o.x, o.y, o.z
            yaw = atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))  # = yaw_from_quaternion
            return cast(Message, kind(ns if ns > 0 else log_time_ns, p.x, p.y, yaw))

        return pose
    return lambda proto, log_time_ns: from_proto(kind, proto, log_time_ns)


# Which schemas each message type can be read from (protobuf and ROS 2).
READABLE_SCHEMAS: dict[type, tuple[str, ...]] = {
    OdometryPose: ("foxglove.PoseInFrame", "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"),
    GroundTruthPose: ("foxglove.PoseInFrame", "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"),
    RangeBearingScan: ("slamreplay.RangeBearingScan",),
    LandmarkMap: ("slamreplay.LandmarkMap",),
    CameraImage: ("foxglove.CompressedImage", "foxglove.RawImage", "sensor_msgs/msg/Image",
                  "sensor_msgs/msg/CompressedImage"),
    CameraCalibration: ("foxglove.CameraCalibration",),
    VelocityCommand: ("slamreplay.VelocityCommand",),
    NavLocalization: ("slamreplay.NavLocalization",),
    ImuYawRate: ("slamreplay.ImuYawRate",),
}
