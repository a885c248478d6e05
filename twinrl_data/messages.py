"""The project's own protobuf messages, for what Foxglove has no well-known schema for.

Built from a descriptor at import (no generated code to keep in sync with the protobuf
runtime); MCAP files carry the schema, so any protobuf reader can decode them.

- ``twinrl.FloatVector``: a step's vector field (state, action, joint targets, ...).
- ``twinrl.Transition``: a step's reward, done, success and intervention flags.
"""

from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2

_FIELD = descriptor_pb2.FieldDescriptorProto


def _build() -> descriptor_pool.DescriptorPool:
    proto = descriptor_pb2.FileDescriptorProto(
        name="twinrl/episode.proto",
        package="twinrl",
        syntax="proto3",
        dependency=["google/protobuf/timestamp.proto"],
    )

    def message(name: str, fields: list[tuple[str, int, int, str | None]]) -> None:
        msg = proto.message_type.add(name=name)
        for number, (field_name, kind, label, type_name) in enumerate(fields, start=1):
            entry = msg.field.add(name=field_name, number=number, type=kind, label=label)
            if type_name:
                entry.type_name = type_name

    optional, repeated = _FIELD.LABEL_OPTIONAL, _FIELD.LABEL_REPEATED
    timestamp = ("timestamp", _FIELD.TYPE_MESSAGE, optional, ".google.protobuf.Timestamp")
    message(
        "FloatVector",
        [
            timestamp,
            ("step", _FIELD.TYPE_UINT32, optional, None),
            ("values", _FIELD.TYPE_FLOAT, repeated, None),
        ],
    )
    message(
        "Transition",
        [
            timestamp,
            ("step", _FIELD.TYPE_UINT32, optional, None),
            ("reward", _FIELD.TYPE_FLOAT, optional, None),
            ("done", _FIELD.TYPE_BOOL, optional, None),
            ("success", _FIELD.TYPE_BOOL, optional, None),
            ("intervention", _FIELD.TYPE_BOOL, optional, None),
        ],
    )
    pool = descriptor_pool.DescriptorPool()
    timestamp_file = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(timestamp_file)
    pool.Add(timestamp_file)
    pool.Add(proto)
    return pool


_POOL = _build()
FloatVector = message_factory.GetMessageClass(_POOL.FindMessageTypeByName("twinrl.FloatVector"))
Transition = message_factory.GetMessageClass(_POOL.FindMessageTypeByName("twinrl.Transition"))
