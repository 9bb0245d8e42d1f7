"""Payloads of a live stream's channels (the Foxglove WebSocket protocol) -> messages or ROS 2 objects.

A channel is advertised with a message encoding, a schema name, a schema encoding and the schema's
bytes, as an MCAP channel is; this module turns one channel's payloads into what the recorder writes:

- ``protobuf`` with a schema slamreplay reads (Foxglove's, slamreplay's): a message, through the same
  :class:`~slamreplay.recorder.codec.TopicDecoder` that reads a recording;
- ``json`` with one of those schema names: the JSON object parsed into the schema's protobuf class
  (Foxglove's JSON timestamps are ``{"sec", "nsec"}`` objects), then read as the protobuf is;
- ``cdr`` with a ``ros2msg`` schema: the decoded ROS 2 object, which the ROS 2 bag importer's conversion
  (:mod:`slamreplay.recorder.importers.ros2bag`) turns into a message, as for a bag.
"""

from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Callable
from typing import Any

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration as CameraCalibrationProto
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage as CompressedImageProto
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame as PoseInFrameProto
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage as RawImageProto
from google.protobuf import json_format
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from slamreplay.recorder.codec import _BAD_MESSAGE, _BAD_SCHEMA, TopicDecoder, _one_line
from slamreplay.recorder.codec.bounds import MAX_JSON_DEPTH, check_ros2_schema, json_depth, shown
from slamreplay.recorder.codec.protobuf import READABLE_SCHEMAS, from_proto
from slamreplay.recorder.codec.schemas import (
    ImuYawRateProto,
    LandmarkMapProto,
    NavLocalizationProto,
    RangeBearingScanProto,
    VelocityCommandProto,
)
from slamreplay.recorder.errors import CodecError
from slamreplay.recorder.messages import Message

_PROTO_CLASSES: dict[str, Any] = {c.DESCRIPTOR.full_name: c for c in (
    PoseInFrameProto, RangeBearingScanProto, LandmarkMapProto, RawImageProto, CompressedImageProto,
    CameraCalibrationProto, VelocityCommandProto, NavLocalizationProto, ImuYawRateProto)}
# JSON and protobuf channels carry these schema names (the ROS 2 names in READABLE_SCHEMAS are read from CDR)
PROTOBUF_SCHEMAS = frozenset(n for names in READABLE_SCHEMAS.values() for n in names if n in _PROTO_CLASSES)
MessageDecoder = Callable[[bytes, int], Message]


def message_decoder(topic: str, kind: type, encoding: str, schema_name: str, schema_encoding: str,
                    schema: bytes) -> MessageDecoder:
    """``decode(payload, fallback_stamp_ns) -> Message`` of type ``kind`` for a protobuf or JSON channel.

    Raises CodecError when the channel's schema cannot give a ``kind`` or is damaged; the decoder raises
    CodecError for a payload that is not a valid message.
    """
    if encoding == "protobuf":
        fds = Schema(id=0, name=schema_name, encoding=schema_encoding or "protobuf", data=schema)
        return TopicDecoder(topic, kind, fds, encoding)
    if encoding != "json":
        raise CodecError(f"topic {shown(topic)}: message encoding {shown(encoding)!r} is not read as a message here "
                         f"(protobuf or json; cdr goes through ros2_decoder)")
    cls = _PROTO_CLASSES.get(schema_name)
    if cls is None or schema_name not in READABLE_SCHEMAS.get(kind, ()):
        raise CodecError(f"topic {shown(topic)}: a JSON {shown(schema_name)} cannot be read as a {kind.__name__}")

    def decode(data: bytes, fallback_stamp_ns: int) -> Message:
        try:
            text = bytes(data).decode()
            if json_depth(text) > MAX_JSON_DEPTH:
                raise CodecError(f"the JSON nests deeper than {MAX_JSON_DEPTH} levels")
            obj = json.loads(text)
            if not isinstance(obj, dict):
                raise CodecError(f"a JSON {type(obj).__name__}, not an object")
            stamp = obj.pop("timestamp", None)
            proto = json_format.ParseDict(obj, cls(), ignore_unknown_fields=True)
            if isinstance(stamp, dict):  # Foxglove's JSON time: {"sec": s, "nsec": ns}
                proto.timestamp.seconds, proto.timestamp.nanos = int(stamp.get("sec", 0)), int(stamp.get("nsec", 0))
            elif isinstance(stamp, str):  # protobuf's JSON time: RFC 3339
                proto.timestamp.FromJsonString(stamp)
            return from_proto(kind, proto, fallback_stamp_ns)
        except (*_BAD_MESSAGE, json_format.ParseError, UnicodeDecodeError) as err:
            raise CodecError(f"{shown(topic)}: a JSON {shown(schema_name)} message is invalid ({len(data)} bytes): "
                             f"{_one_line(err) or type(err).__name__}") from err

    return decode


def ros2_decoder(topic: str, schema_name: str, schema: bytes) -> Callable[[bytes], Any]:
    """``decode(cdr_bytes) -> object`` for a ``cdr`` channel with a ``ros2msg`` schema (the concatenated
    definition, as in MCAP and as ``foxglove_bridge`` advertises it). CodecError for a damaged schema; the
    decoder raises CodecError for bytes that do not decode."""
    try:
        text = schema.decode()
        check_ros2_schema(text, schema_name)
        with contextlib.redirect_stderr(io.StringIO()):  # rosidl's parser prints each bad line before it raises
            msgdef = Schema(id=0, name=schema_name, encoding="ros2msg", data=schema)
            raw = Ros2DecoderFactory().decoder_for("cdr", msgdef)
    except _BAD_SCHEMA as err:
        raise CodecError(f"topic {shown(topic)}: its schema {shown(schema_name)} (ros2msg, {len(schema)} bytes) "
                         f"cannot be parsed: {type(err).__name__}: {_one_line(err)}") from err
    if raw is None:
        raise CodecError(f"topic {shown(topic)}: schema {shown(schema_name)} cannot be decoded from CDR")

    def decode(data: bytes) -> Any:
        try:
            return raw(bytes(data))
        except _BAD_MESSAGE as err:
            raise CodecError(f"{shown(topic)}: a {shown(schema_name)} message does not decode ({len(data)} bytes): "
                             f"{_one_line(err) or type(err).__name__}") from err

    return decode
