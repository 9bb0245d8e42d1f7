"""The codec: the only code in slamreplay that touches message bytes.

Writing uses protobuf with the Foxglove well-known schemas and slamreplay's custom schemas
(:mod:`slamreplay.recorder.codec.schemas`). Reading accepts those and ROS 2 (``ros2msg``/CDR) messages.
A :class:`TopicDecoder` is made once per channel and turns its raw bytes into messages.
"""

from __future__ import annotations

import contextlib
import io
import struct
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2._vendor.rosidl_adapter.parser import InvalidSpecification, InvalidValue
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from slamreplay.recorder.codec.bounds import check_protobuf_schema, check_ros2_schema, shown
from slamreplay.recorder.codec.protobuf import READABLE_SCHEMAS, encode, proto_converter, schema_data, schema_name
from slamreplay.recorder.codec.ros2 import canonical_ros_type, from_ros2
from slamreplay.recorder.errors import CodecError
from slamreplay.recorder.messages import LandmarkMap, Message, PlanarPose, RangeBearingScan

__all__ = ["READABLE_SCHEMAS", "TopicDecoder", "encode", "schema_data", "schema_name"]

# What a damaged schema raises while it is parsed: a FileDescriptorSet that is not protobuf
# (DecodeError), whose files do not build (TypeError from the descriptor pool), a ros2msg text
# that is not UTF-8 (UnicodeDecodeError, a ValueError) or not message definitions (rosidl's
# InvalidSpecification family, NameError for a bad field name).
_BAD_SCHEMA = (CodecError, DecodeError, TypeError, ValueError, KeyError, IndexError, NameError, McapError,
               InvalidSpecification, InvalidValue)
# What damaged message bytes raise: protobuf's DecodeError, CDR reads past the end (struct.error,
# IndexError), bad UTF-8 or values the message model refuses (ValueError), an image OpenCV cannot take,
# and a damaged schema that still parses but lost a field the message model reads (AttributeError).
_BAD_MESSAGE = (CodecError, DecodeError, McapError, struct.error, ValueError, TypeError, IndexError, KeyError,
                OverflowError, AttributeError, cv2.error)


class TopicDecoder:
    """Decodes the messages of one channel into messages of type ``kind``.

    Raises CodecError at construction when the channel's schema cannot give a ``kind``,
    and on call when a message's bytes or values are bad (NaN, wrong shapes...).
    """

    def __init__(self, topic: str, kind: type, schema: Schema | None, message_encoding: str) -> None:
        self.topic, self.kind = topic, kind
        name = "" if schema is None else schema.name
        readable = READABLE_SCHEMAS[kind]
        if canonical_ros_type(name) not in readable:
            msg = (f"topic {shown(topic)} has schema {shown(name) or '(none)'} with encoding "
                   f"{shown(message_encoding)!r}; "
                   f"a {kind.__name__} is read from one of: {', '.join(readable)}")
            raise CodecError(msg)
        assert schema is not None
        self.schema_name = name
        self._raw: Callable[[bytes], Any] | None
        try:
            if message_encoding == "protobuf" and schema.encoding == "protobuf":
                check_protobuf_schema(schema.data)  # bounded before the library builds (and recurses)
                self._raw = ProtobufDecoderFactory().decoder_for(message_encoding, schema)
                self._ros = False
                self._convert = proto_converter(kind, name)
            elif message_encoding == "cdr" and schema.encoding == "ros2msg":
                check_ros2_schema(schema.data.decode(), name)  # bounded before the library builds (and recurses)
                # rosidl's parser prints each bad line to stderr before it raises: the error below says it once
                with contextlib.redirect_stderr(io.StringIO()):
                    self._raw = Ros2DecoderFactory().decoder_for(message_encoding, schema)
                self._ros = True
            else:
                self._raw = None
        except _BAD_SCHEMA as err:
            msg = (f"topic {shown(topic)}: its schema {shown(name)} ({shown(schema.encoding)}, {len(schema.data)} "
                   f"bytes) is damaged "
                   f"and cannot be parsed: {type(err).__name__}: {_one_line(err)}")
            raise CodecError(msg) from err
        if self._raw is None:
            msg = (f"topic {shown(topic)}: schema {shown(name)} with schema encoding {shown(schema.encoding)!r} and "
                   f"message encoding {shown(message_encoding)!r} is not supported (use protobuf, or ROS 2 "
                   f"ros2msg/cdr)")
            raise CodecError(msg)

    def __call__(self, data: bytes, log_time_ns: int) -> Message:
        assert self._raw is not None
        try:
            obj = self._raw(data)
            if self._ros:
                decoded = from_ros2(self.kind, self.schema_name, obj, log_time_ns)
            else:
                decoded = self._convert(obj, log_time_ns)
            _check_plausible(decoded)
            return decoded
        except _BAD_MESSAGE as err:
            msg = (f"{shown(self.topic)} message at log_time {log_time_ns} ns is invalid ({len(data)} bytes): "
                   f"{_one_line(err) or type(err).__name__}")
            raise CodecError(msg) from err


# No robot recording holds a coordinate or range this far out; bytes shifted by damage easily decode into one
# (1e300 is finite), which then overflows the float32 of the viewer and the algorithms' arithmetic.
PLAUSIBLE_M = 1e9


def _check_plausible(msg: Message) -> None:
    """CodecError when a decoded position or range is beyond PLAUSIBLE_M metres."""
    if isinstance(msg, PlanarPose):  # scalars: plain floats, not numpy (this runs for every decoded pose)
        for name, x in (("x_m", msg.x_m), ("y_m", msg.y_m)):
            if abs(x) > PLAUSIBLE_M:
                raise CodecError(f"{name} holds {abs(x):.3g} m, beyond any plausible {PLAUSIBLE_M:g} m: "
                                 f"the bytes are damaged")
        return
    if isinstance(msg, RangeBearingScan):
        values = {"ranges_m": msg.ranges_m}
    elif isinstance(msg, LandmarkMap):
        values = {"positions_m": msg.positions_m}
    else:
        return
    for name, v in values.items():
        if v.size and float(np.max(np.abs(v))) > PLAUSIBLE_M:
            raise CodecError(f"{name} holds {float(np.max(np.abs(v))):.3g} m, beyond any plausible "
                             f"{PLAUSIBLE_M:g} m: the bytes are damaged")


def _one_line(err: BaseException, limit: int = 200) -> str:
    """An exception's text on one line, printable and bounded (damaged bytes can end up in it)."""
    text = " ".join(str(err).split())
    text = "".join(c if c.isprintable() else "?" for c in text)
    return text if len(text) <= limit else text[:limit] + "..."
