"""The codec: the only code in slamreplay that touches message bytes.

Writing uses protobuf with the Foxglove well-known schemas and slamreplay's custom schemas
(:mod:`recorder.codec.schemas`). Reading accepts those and ROS 2 (``ros2msg``/CDR) messages.
A :class:`TopicDecoder` is made once per channel and turns its raw bytes into messages.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from recorder.codec.protobuf import READABLE_SCHEMAS, encode, from_proto, schema_data, schema_name
from recorder.codec.ros2 import canonical_ros_type, from_ros2
from recorder.errors import CodecError
from recorder.messages import Message

__all__ = ["READABLE_SCHEMAS", "TopicDecoder", "encode", "schema_data", "schema_name"]


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
            msg = (f"topic {topic} has schema {name or '(none)'} with encoding {message_encoding!r}; "
                   f"a {kind.__name__} is read from one of: {', '.join(readable)}")
            raise CodecError(msg)
        assert schema is not None
        self.schema_name = name
        self._raw: Callable[[bytes], Any] | None
        if message_encoding == "protobuf" and schema.encoding == "protobuf":
            self._raw = ProtobufDecoderFactory().decoder_for(message_encoding, schema)
            self._ros = False
        elif message_encoding == "cdr" and schema.encoding == "ros2msg":
            self._raw = Ros2DecoderFactory().decoder_for(message_encoding, schema)
            self._ros = True
        else:
            self._raw = None
        if self._raw is None:
            msg = (f"topic {topic}: schema {name} with schema encoding {schema.encoding!r} and message "
                   f"encoding {message_encoding!r} is not supported (use protobuf, or ROS 2 ros2msg/cdr)")
            raise CodecError(msg)

    def __call__(self, data: bytes, log_time_ns: int) -> Message:
        assert self._raw is not None
        try:
            obj = self._raw(data)
            if self._ros:
                return from_ros2(self.kind, self.schema_name, obj, log_time_ns)
            return from_proto(self.kind, obj, log_time_ns)
        except Exception as err:
            msg = f"{self.topic} message at log_time {log_time_ns} ns is invalid: {err}"
            raise CodecError(msg) from err
