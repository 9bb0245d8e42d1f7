"""Custom protobuf schemas, built as descriptors in code (no protoc step).

``slamreplay.RangeBearingScan`` and ``slamreplay.LandmarkMap`` follow the Foxglove style:
a ``google.protobuf.Timestamp timestamp`` and a ``frame_id`` first, then the payload as
packed repeated fields. Field numbers are part of the format: never renumber them.
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2

PACKAGE = "slamreplay"
FILE_NAME = "slamreplay/landmarks.proto"
NAV_FILE_NAME = "slamreplay/navigation.proto"

_F = descriptor_pb2.FieldDescriptorProto

# (name, number, type, label, type_name)
_RANGE_BEARING_FIELDS = [
    ("timestamp", 1, _F.TYPE_MESSAGE, _F.LABEL_OPTIONAL, ".google.protobuf.Timestamp"),
    ("frame_id", 2, _F.TYPE_STRING, _F.LABEL_OPTIONAL, None),
    ("ranges", 3, _F.TYPE_DOUBLE, _F.LABEL_REPEATED, None),  # metres
    ("bearings", 4, _F.TYPE_DOUBLE, _F.LABEL_REPEATED, None),  # radians, CCW from +x
    ("landmark_ids", 5, _F.TYPE_INT64, _F.LABEL_REPEATED, None),  # -1 = unknown
    ("range_sigma", 6, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # metres, 1-sigma
    ("bearing_sigma", 7, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # radians, 1-sigma
]
_LANDMARK_MAP_FIELDS = [
    ("timestamp", 1, _F.TYPE_MESSAGE, _F.LABEL_OPTIONAL, ".google.protobuf.Timestamp"),
    ("frame_id", 2, _F.TYPE_STRING, _F.LABEL_OPTIONAL, None),
    ("landmark_ids", 3, _F.TYPE_INT64, _F.LABEL_REPEATED, None),
    ("x", 4, _F.TYPE_DOUBLE, _F.LABEL_REPEATED, None),  # metres
    ("y", 5, _F.TYPE_DOUBLE, _F.LABEL_REPEATED, None),  # metres
]
_IMU_YAW_RATE_FIELDS = [
    ("timestamp", 1, _F.TYPE_MESSAGE, _F.LABEL_OPTIONAL, ".google.protobuf.Timestamp"),
    ("frame_id", 2, _F.TYPE_STRING, _F.LABEL_OPTIONAL, None),
    ("yaw_rate", 3, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # rad/s, counter-clockwise about +z of the body
    ("yaw_rate_sigma", 4, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # rad/s, 1-sigma, 0 = not stated
]

# Navigation (topo-metric navigation mode): a velocity command (foxglove has no Twist) and the
# localization after each image.
_VELOCITY_COMMAND_FIELDS = [
    ("timestamp", 1, _F.TYPE_MESSAGE, _F.LABEL_OPTIONAL, ".google.protobuf.Timestamp"),
    ("frame_id", 2, _F.TYPE_STRING, _F.LABEL_OPTIONAL, None),
    ("linear", 3, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # m/s, forward (+x of base_link)
    ("angular", 4, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # rad/s, counter-clockwise about +z
]
_NAV_LOCALIZATION_FIELDS = [
    ("timestamp", 1, _F.TYPE_MESSAGE, _F.LABEL_OPTIONAL, ".google.protobuf.Timestamp"),
    ("frame_id", 2, _F.TYPE_STRING, _F.LABEL_OPTIONAL, None),
    ("x", 3, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # metres
    ("y", 4, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # metres
    ("yaw", 5, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # radians, CCW from +x
    ("node", 6, _F.TYPE_INT64, _F.LABEL_OPTIONAL, None),  # matched map node, -1 = none
    ("x_translation", 7, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # pixels
    ("heading_deviation", 8, _F.TYPE_DOUBLE, _F.LABEL_OPTIONAL, None),  # radians
    ("corrected", 9, _F.TYPE_BOOL, _F.LABEL_OPTIONAL, None),
]


def _add_messages(fdp: descriptor_pb2.FileDescriptorProto, messages: list[tuple[str, list[Any]]]) -> None:
    for msg_name, msg_fields in messages:
        msg = fdp.message_type.add(name=msg_name)
        for name, number, ftype, label, type_name in msg_fields:
            field = msg.field.add(name=name, number=number, type=ftype, label=label, json_name=name)
            if type_name:
                field.type_name = type_name


def _nav_file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    fdp = descriptor_pb2.FileDescriptorProto(
        name=NAV_FILE_NAME, package=PACKAGE, syntax="proto3", dependency=["google/protobuf/timestamp.proto"]
    )
    _add_messages(fdp, [("VelocityCommand", _VELOCITY_COMMAND_FIELDS), ("NavLocalization", _NAV_LOCALIZATION_FIELDS)])
    return fdp


def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    fdp = descriptor_pb2.FileDescriptorProto(
        name=FILE_NAME, package=PACKAGE, syntax="proto3", dependency=["google/protobuf/timestamp.proto"]
    )
    for msg_name, msg_fields in (("RangeBearingScan", _RANGE_BEARING_FIELDS), ("LandmarkMap", _LANDMARK_MAP_FIELDS),
                                  ("ImuYawRate", _IMU_YAW_RATE_FIELDS)):
        msg = fdp.message_type.add(name=msg_name)
        for name, number, ftype, label, type_name in msg_fields:
            field = msg.field.add(name=name, number=number, type=ftype, label=label, json_name=name)
            if type_name:
                field.type_name = type_name
    return fdp


def _build_classes() -> dict[str, Any]:
    pool = descriptor_pool.DescriptorPool()
    ts = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(ts)
    pool.Add(ts)
    pool.Add(_file_descriptor())
    pool.Add(_nav_file_descriptor())
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{name}"))
        for name in ("RangeBearingScan", "LandmarkMap", "VelocityCommand", "NavLocalization", "ImuYawRate")
    }


_CLASSES = _build_classes()
RangeBearingScanProto: Any = _CLASSES["RangeBearingScan"]
LandmarkMapProto: Any = _CLASSES["LandmarkMap"]
VelocityCommandProto: Any = _CLASSES["VelocityCommand"]
NavLocalizationProto: Any = _CLASSES["NavLocalization"]
ImuYawRateProto: Any = _CLASSES["ImuYawRate"]
