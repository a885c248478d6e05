"""Episodes as MCAP files: the raw log written while recording.

One file per episode. Channels (all protobuf):

==================================  ===========================  ==========================
topic                               schema                       content
==================================  ===========================  ==========================
/observation/state                  twinrl.FloatVector           ``observation.state``
/observation/environment_state      twinrl.FloatVector           object poses (if logged)
/action, /action/policy             twinrl.FloatVector           executed / proposed action
/command/joint_target               twinrl.FloatVector           servo targets
/transition                         twinrl.Transition            reward, done, success, ...
/camera/<name>                      foxglove.CompressedImage     JPEG (default) or PNG
/camera/<name> (a live episode's)   foxglove.CompressedVideo     H.264, every frame a key
/tf                                 foxglove.FrameTransforms     TCP and object poses
/samples/<stream>                   twinrl.FloatVector           a live episode's samples
==================================  ===========================  ==========================

A live episode (a real cell's, :mod:`twinrl_data.streams`) has every camera frame at the
camera's rate and sample streams (the controller's state at 500 Hz), all on the host's
clock; its ``twinrl.streams`` metadata record names them.

Episode metadata is an MCAP metadata record ``twinrl.episode`` written when recording
starts (values JSON-encoded), and ``twinrl.episode_end`` when it ends. The writer closes
a chunk every ``flush_seconds`` of log time, so a recorder killed mid-episode loses at
most that much; :func:`recover` rewrites a truncated file into a valid one.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import math
import os
from collections import defaultdict
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import PIL.Image
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.well_known import MessageEncoding
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

from twinrl_data import schema as contract
from twinrl_data.atomic import disk_error
from twinrl_data.errors import DataError, McapError
from twinrl_data.live_video import decode_frame
from twinrl_data.messages import FloatVector, Transition
from twinrl_data.step_frames import frames_of_steps

TOPICS = {
    contract.STATE: "/observation/state",
    contract.ENVIRONMENT_STATE: "/observation/environment_state",
    contract.EFFORT: "/observation/effort",
    contract.WRENCH: "/observation/wrench",
    contract.CONTROLLER_TIME: "/observation/controller_time",
    contract.CONTROLLER_TARGET: "/observation/controller_target",
    contract.ACTION: "/action",
    contract.ACTION_POLICY: "/action/policy",
    contract.JOINT_TARGET: "/command/joint_target",
}
FIELD_OF_TOPIC = {topic: name for name, topic in TOPICS.items()}
TRANSITION_TOPIC = "/transition"
TF_TOPIC = "/tf"
CAMERA_PREFIX = "/camera/"
BASE_FRAME = "base"
META_START = "twinrl.episode"
META_FIELDS = "twinrl.fields"
META_END = "twinrl.episode_end"
META_STREAMS = "twinrl.streams"  # a live episode's cameras and sample streams, at their rates
POSE_SUFFIXES = ("x", "y", "z", "qw", "qx", "qy", "qz")
# a camera topic's messages: a step's image, or a live episode's H.264 frame
CAMERA_SCHEMAS = {
    "foxglove.CompressedImage": CompressedImage,
    "foxglove.CompressedVideo": CompressedVideo,
}
IMAGE_FORMATS = ("jpeg", "png")


def pose_groups(names: list[str]) -> dict[str, list[int]]:
    """Frames whose full pose (x, y, z, qw, qx, qy, qz) appears in ``names``: indices."""
    index = {name: i for i, name in enumerate(names)}
    groups = {}
    for name in names:
        if name.endswith(".x"):
            frame = name[:-2]
            keys = [f"{frame}.{s}" for s in POSE_SUFFIXES]
            if all(k in index for k in keys):
                groups[frame] = [index[k] for k in keys]
    return groups


class EpisodeWriter:
    """Streams one episode into an MCAP file, one :meth:`append` per control step.

    Use as a context manager::

        with EpisodeWriter(path, meta) as log:
            for ...:
                log.append({"observation.state": s, "action": a, ...})

    Steps are dicts keyed by contract field (see :mod:`twinrl_data.schema`); every
    problem of a malformed step is reported in one :class:`~twinrl_data.errors.DataError`.
    ``on_close`` is called with the final metadata, the steps written and the status
    (``complete``, or ``partial`` after a failed write; used by sessions' manifests).

    A write that fails (a full disk, an I/O error) stops the episode: what was written
    is kept as a partial episode (:func:`twinrl_data.salvage.recover` makes a valid file
    of it), the status goes to ``on_close``, and the error is one
    :class:`~twinrl_data.errors.DataError`.
    """

    def __init__(
        self,
        path: str | Path,
        meta: contract.EpisodeMeta,
        *,
        image_format: str = "jpeg",
        jpeg_quality: int = 90,
        flush_seconds: float = 1.0,
        start_ns: int | None = None,
        overwrite: bool = False,
        on_close: Callable[[contract.EpisodeMeta, int, str], None] | None = None,
    ) -> None:
        if image_format not in IMAGE_FORMATS:
            raise McapError(f"image_format must be one of {IMAGE_FORMATS}, got '{image_format}'")
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise McapError(f"{self.path} already exists; refusing to overwrite it")
        self.meta = meta
        self.image_format = image_format
        self.jpeg_quality = jpeg_quality
        # 0: the owner flushes (a live episode, by its own clock; see twinrl_data.streams)
        self._flush_every = max(1, math.ceil(flush_seconds * meta.fps)) if flush_seconds else 0
        self._period_ns = round(1e9 / meta.fps)
        self._start_ns = start_ns if start_ns is not None else _iso_to_ns(meta.created_at)
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            raise McapError(f"{self.path} already exists; refusing to overwrite it") from None
        except OSError as err:
            raise disk_error(err, self.path) from None
        self._file = os.fdopen(fd, "wb")
        # CRCs over every chunk and over the whole data section (metadata included), so
        # that a reader refuses a damaged byte anywhere instead of returning wrong data.
        self._writer = Writer(
            self._file, compression=CompressionType.ZSTD, enable_crcs=True, enable_data_crcs=True
        )
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._shapes: dict[str, tuple[int, ...]] = {}
        self._fields: set[str] = set()
        self._poses: dict[str, dict[str, list[int]]] = {
            key: pose_groups(meta.names.get(key, []))
            for key in (contract.STATE, contract.ENVIRONMENT_STATE)
        }
        self._on_close = on_close
        self.steps = 0
        self.interventions = 0
        self.last_success = False
        self._closed = False
        self._guarded(self._begin)

    def _begin(self) -> None:
        self._writer.start(profile="twinrl", library="twinrl")
        self._writer.add_metadata(META_START, _encode(self.meta.to_dict()))
        self._writer.flush()

    def _guarded(self, write: Callable[[], None]) -> None:
        """Run ``write``; a failed write closes the episode as partial (class docstring)."""
        try:
            write()
        except OSError as err:
            self._closed = True
            with contextlib.suppress(OSError):
                self._file.close()
            if self._on_close is not None:
                self._on_close(self.meta, self.steps, "partial")
            raise DataError(
                f"{disk_error(err, self.path)}; the {self.steps} steps written so far are kept "
                "as a partial episode (`twinrl data repair` on its session recovers it)"
            ) from None

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _channel(self, topic: str, message_class: Any) -> int:
        if topic not in self._channels:
            name = message_class.DESCRIPTOR.full_name
            if name not in self._schemas:
                self._schemas[name] = register_schema(self._writer, message_class)
            self._channels[topic] = self._writer.register_channel(
                topic=topic,
                message_encoding=MessageEncoding.Protobuf,
                schema_id=self._schemas[name],
            )
        return self._channels[topic]

    def _write(self, topic: str, message: Any, time_ns: int, sequence: int | None = None) -> None:
        channel = self._channel(topic, type(message))
        self._writer.add_message(
            channel_id=channel,
            log_time=time_ns,
            publish_time=time_ns,
            data=message.SerializeToString(),
            sequence=self.steps if sequence is None else sequence,
        )

    def append(self, step: Mapping[str, Any], time_ns: int | None = None) -> None:
        """Log one control step (observation, action and what it led to) at ``time_ns``
        on the episode's clock (default: the step's place at the episode's rate)."""
        if self._closed:
            raise McapError(f"{self.path}: episode already closed; start a new EpisodeWriter")
        contract.validate_step(step, self._shapes)
        self._guarded(lambda: self._write_step(step, time_ns))

    def write(self, topic: str, message: Any, time_ns: int, sequence: int) -> None:
        """Log one message of a stream at its own rate (see :mod:`twinrl_data.streams`)."""
        if self._closed:
            raise McapError(f"{self.path}: episode already closed; start a new EpisodeWriter")
        self._guarded(lambda: self._write(topic, message, time_ns, sequence))

    def add_metadata(self, name: str, values: Mapping[str, Any]) -> None:
        """Write a metadata record (values JSON-encoded)."""
        self._guarded(lambda: self._writer.add_metadata(name, _encode(values)))

    def flush(self) -> None:
        """Close the open chunk: what was written so far survives a crash."""
        self._guarded(self._writer.flush)

    def _write_step(self, step: Mapping[str, Any], time_ns: int | None) -> None:
        if self.steps == 0:
            self._shapes = {k: np.shape(v) for k, v in step.items() if k in contract.VECTOR_FIELDS}
            fields = sorted(k for k, v in step.items() if v is not None)
            if contract.ACTION_POLICY not in fields:
                fields.append(contract.ACTION_POLICY)  # defaults to the executed action
            self._fields = set(fields)
            self._writer.add_metadata(META_FIELDS, _encode({"fields": sorted(fields)}))
        if time_ns is None:
            time_ns = self._start_ns + self.steps * self._period_ns
        for key, topic in TOPICS.items():
            value = step.get(key)
            if key == contract.ACTION_POLICY and value is None:
                value = step[contract.ACTION]
            if value is None:
                continue
            vector = FloatVector(step=self.steps, values=np.asarray(value, np.float32).tolist())
            vector.timestamp.FromNanoseconds(time_ns)
            self._write(topic, vector, time_ns)
        intervention = bool(step.get(contract.INTERVENTION, False))
        if any(key in self._fields for key in contract.SCALAR_FIELDS):
            transition = Transition(
                step=self.steps,
                reward=float(step.get(contract.REWARD, 0.0)),
                done=bool(step.get(contract.DONE, False)),
                success=bool(step.get(contract.SUCCESS, False)),
                intervention=intervention,
            )
            transition.timestamp.FromNanoseconds(time_ns)
            self._write(TRANSITION_TOPIC, transition, time_ns)
        for key, value in step.items():
            if key.startswith(contract.IMAGES_PREFIX):
                camera = key[len(contract.IMAGES_PREFIX) :]
                image = CompressedImage(
                    frame_id=camera, format=self.image_format, data=self._encode(value)
                )
                image.timestamp.FromNanoseconds(time_ns)
                self._write(CAMERA_PREFIX + camera, image, time_ns)
        self._write_poses(step, time_ns)
        self.interventions += intervention
        self.last_success = bool(step.get(contract.SUCCESS, False))
        self.steps += 1
        if self._flush_every and self.steps % self._flush_every == 0:
            self._writer.flush()  # closes the chunk: a crash loses at most flush_seconds

    def _write_poses(self, step: Mapping[str, Any], time_ns: int) -> None:
        transforms = FrameTransforms()
        for key, groups in self._poses.items():
            values = step.get(key)
            if values is None:
                continue
            for frame, idx in groups.items():
                x, y, z, qw, qx, qy, qz = (float(values[i]) for i in idx)
                tf = FrameTransform(parent_frame_id=BASE_FRAME, child_frame_id=frame)
                tf.timestamp.FromNanoseconds(time_ns)
                tf.translation.x, tf.translation.y, tf.translation.z = x, y, z
                tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z = qw, qx, qy, qz
                transforms.transforms.append(tf)
        if transforms.transforms:
            self._write(TF_TOPIC, transforms, time_ns)

    def _encode(self, image: np.ndarray) -> bytes:
        buffer = io.BytesIO()
        pil = PIL.Image.fromarray(np.asarray(image, np.uint8))
        if self.image_format == "jpeg":
            pil.save(buffer, format="JPEG", quality=self.jpeg_quality)
        else:
            pil.save(buffer, format="PNG", compress_level=1)
        return buffer.getvalue()

    def close(
        self,
        success: bool | None = None,
        aborted: str | None = None,
        sensors: Mapping[str, Any] | None = None,
        note: str | None = None,
    ) -> contract.EpisodeMeta:
        """Finish the file; ``success`` defaults to the last step's ``next.success``;
        ``aborted`` says why the episode ended early (kept with its data); ``sensors``
        what the cell's sensors delivered; ``note`` a person's words about it."""
        if self._closed:
            return self.meta
        final_success = self.last_success if success is None else bool(success)
        self.meta = self.meta.replace(
            success=final_success,
            num_interventions=self.interventions,
            aborted=aborted,
            sensors=dict(sensors or {}),
            note=note,
        )
        end = {
            "success": final_success,
            "num_interventions": self.interventions,
            "length": self.steps,
            "aborted": aborted,
            "sensors": dict(sensors or {}),
            "note": note,
        }
        self._guarded(lambda: self._finish(end))
        self._closed = True
        if self._on_close is not None:
            self._on_close(self.meta, self.steps, "complete")
        return self.meta

    def _finish(self, end: Mapping[str, Any]) -> None:
        self._writer.add_metadata(META_END, _encode(end))
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()


def _encode(values: Mapping[str, Any]) -> dict[str, str]:
    return {key: json.dumps(value) for key, value in values.items()}


def _decode(values: Mapping[str, str]) -> dict[str, Any]:
    return {key: json.loads(value) for key, value in values.items()}


def _iso_to_ns(text: str) -> int:
    return int(dt.datetime.fromisoformat(text).timestamp() * 1e9)


RECOVERED_BY = "twinrl recover"  # the writer library of files ``data recover`` wrote


def _open_checked(path: str | Path) -> Path:
    path = Path(path)
    if path.is_dir():
        raise McapError(
            f"{path} is a folder, not an episode file; give one of its .mcap files (a session "
            "folder is read whole by the commands that take sessions)"
        )
    if not path.is_file():
        raise McapError(f"{path} does not exist (expected an episode .mcap file)")
    with open(path, "rb") as f:
        head = f.read(8)
    if head != b"\x89MCAP0\r\n":
        raise McapError(f"{path} is not an MCAP file (bad magic bytes)")
    return path


def intact_records(stream: IO[bytes], damaged: Callable[[Chunk], None]) -> Iterator[Any]:
    """Every record of an MCAP stream, chunks broken up, every checksum checked (each
    chunk's and, at its end, the data section's). A chunk that fails goes to
    ``damaged``, which raises to stop the reading or returns to skip the chunk."""
    for record in StreamReader(stream, validate_crcs=True, emit_chunks=True).records:
        if not isinstance(record, Chunk):
            yield record
            continue
        try:
            parts = breakup_chunk(record, validate_crc=True)
        except Exception:
            damaged(record)
            continue
        yield from parts


def _chunk_damage(path: Path, chunk: Chunk, records: Mapping[str, Any]) -> McapError:
    """A damaged chunk (its checksum or compression broken) as one line: which episode,
    and which span of it is lost."""
    span = "a chunk of its steps is damaged"
    if META_START in records:
        start = _iso_to_ns(records[META_START]["created_at"])
        first = (chunk.message_start_time - start) / 1e9
        last = (chunk.message_end_time - start) / 1e9
        span = f"the steps logged from {first:.1f} s to {last:.1f} s are damaged"
    return McapError(
        f"{path} is damaged: {span}; `twinrl data recover {path}` writes what is intact "
        "to a new file"
    )


def _damaged(path: Path, err: Exception) -> McapError:
    return McapError(
        f"{path} is truncated or damaged ({type(err).__name__}: {err}); "
        f"`twinrl data recover {path}` rewrites what can still be read"
    )


def read_meta(path: str | Path) -> contract.EpisodeMeta:
    """The episode metadata of an MCAP file (the end record's results merged in).

    Reads the metadata records only (through the file's summary), so it is quick; a
    damaged byte elsewhere shows when the episode is read (:func:`read_episode`)."""
    path = _open_checked(path)
    try:
        with open(path, "rb") as f:
            records = {m.name: _decode(m.metadata) for m in make_reader(f).iter_metadata()}
    except Exception as err:
        raise _damaged(path, err) from None
    return _meta_from(path, records)


@dataclass(frozen=True)
class Summary:
    """What an episode file says about itself without its steps."""

    meta: contract.EpisodeMeta
    length: int | None  # steps, from the end record; None: the recording never finished


def read_summary(path: str | Path) -> Summary:
    """The metadata of an episode file, finished or not.

    A file counts as finished only when it has its end record *and* runs to the MCAP
    footer: the end record is written before the last chunk of steps and the summary,
    so a recorder killed while finishing leaves a file with an end record that is not
    whole (``length`` is ``None`` for it, as for a file with no end record)."""
    path = _open_checked(path)
    records: dict[str, dict[str, Any]] = {}
    whole = False
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
                if isinstance(record, Metadata):
                    records[record.name] = _decode(record.metadata)
        whole = True
    except Exception as err:
        if META_START not in records:
            raise _damaged(path, err) from None
    end = records.get(META_END)
    length = int(end["length"]) if end is not None and whole else None
    return Summary(_meta_from(path, records), length)


def _meta_from(path: Path, records: Mapping[str, dict[str, Any]]) -> contract.EpisodeMeta:
    if META_START not in records:
        raise McapError(f"{path} has no '{META_START}' metadata: not a twinrl episode log")
    meta = contract.EpisodeMeta.from_dict(records[META_START])
    end = records.get(META_END)
    if end is not None:
        meta = meta.replace(
            success=end["success"],
            num_interventions=end["num_interventions"],
            aborted=end.get("aborted"),
            sensors=end.get("sensors", {}),
            note=end.get("note"),
        )
    return meta


def read_episode(path: str | Path, *, images: bool = True) -> contract.Episode:
    """Read a whole episode: metadata and every field in step order (a live episode's
    sample streams too: :func:`twinrl_data.streams.read_live_episode`).

    Raises :class:`~twinrl_data.errors.McapError` for a missing, non-MCAP, truncated or
    foreign file (never another exception type).
    """
    path = _open_checked(path)
    vectors: dict[str, dict[int, np.ndarray]] = defaultdict(dict)
    transitions: dict[int, Any] = {}
    frames: dict[str, dict[int, tuple[int, bytes]]] = defaultdict(dict)
    step_times: list[int] = []  # ns, the state's, in step order
    records: dict[str, dict[str, Any]] = {}
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}

    def damaged(chunk: Chunk) -> None:
        raise _chunk_damage(path, chunk, records)

    library = ""
    checked = False  # the data section's end (and so its checksum) was reached
    try:
        with open(path, "rb") as f:
            for record in intact_records(f, damaged):
                if isinstance(record, Header):
                    library = record.library
                elif isinstance(record, DataEnd):
                    checked = True
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is not None:
                        schema = schemas.get(channel.schema_id)
                        _collect(schema, channel, record, vectors, transitions, frames, images)
                        if channel.topic == TOPICS[contract.STATE]:
                            step_times.append(record.log_time)
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Metadata):
                    records[record.name] = _decode(record.metadata)
    except McapError:
        raise
    except Exception as err:
        raise _damaged(path, err) from None
    if not checked or (META_END not in records and library != RECOVERED_BY):
        # A damaged record length can make the reader jump over the rest of the data
        # section (the end record and the checksum with it) and land on the summary.
        raise McapError(
            f"{path} is damaged: its data section does not end as written (a corrupt record "
            f"skips past it); `twinrl data recover {path}` rewrites what can still be read"
        )
    meta = _meta_from(path, records)
    if contract.STATE not in vectors:
        raise McapError(
            f"{path} has no {TOPICS[contract.STATE]} messages: no complete step was logged"
        )
    streamed = records.get(META_STREAMS, {}).get("cameras", {})
    frames = {cam: frames_of_steps(rows, step_times) if cam in streamed else rows
              for cam, rows in frames.items()}  # fmt: skip
    streams = [*vectors.values(), *frames.values()] + ([transitions] if transitions else [])
    steps = _complete_steps(vectors[contract.STATE], streams)
    fields = set(records.get(META_FIELDS, {}).get("fields", contract.SCALAR_FIELDS))
    data: dict[str, np.ndarray] = {}
    for key, rows in vectors.items():
        data[key] = np.stack([rows[s] for s in steps]) if steps else np.zeros((0, 0), np.float32)
    if transitions:
        for key, attribute, dtype in (
            (contract.REWARD, "reward", np.float32),
            (contract.DONE, "done", bool),
            (contract.SUCCESS, "success", bool),
            (contract.INTERVENTION, "intervention", bool),
        ):
            if key in fields:
                data[key] = np.array([getattr(transitions[s], attribute) for s in steps], dtype)
    camera_arrays = {
        cam: np.stack([decode_frame(rows[s][1]) for s in steps])
        for cam, rows in frames.items()
        if steps
    }
    return contract.Episode(meta=meta, data=data, images=camera_arrays)


def _complete_steps(states: Mapping[int, Any], streams: list[Mapping[int, Any]]) -> list[int]:
    """Steps 0..k-1 for the largest k such that every stream has all of them.

    A recorder killed mid-step leaves a partial last step; it is dropped.
    """
    count = 0
    while count in states and all(count in stream for stream in streams):
        count += 1
    return list(range(count))


def _collect(
    schema: Schema | None,
    channel: Channel,
    message: Message,
    vectors: dict[str, dict[int, np.ndarray]],
    transitions: dict[int, Any],
    frames: dict[str, dict[int, tuple[int, bytes]]],
    images: bool,
) -> None:
    name = schema.name if schema is not None else ""
    if channel.topic in FIELD_OF_TOPIC and name == "twinrl.FloatVector":
        vector = FloatVector.FromString(message.data)
        vectors[FIELD_OF_TOPIC[channel.topic]][vector.step] = np.asarray(vector.values, np.float32)
    elif channel.topic == TRANSITION_TOPIC and name == "twinrl.Transition":
        transition = Transition.FromString(message.data)
        transitions[transition.step] = transition
    elif images and channel.topic.startswith(CAMERA_PREFIX) and name in CAMERA_SCHEMAS:
        image = CAMERA_SCHEMAS[name].FromString(message.data)
        camera = channel.topic[len(CAMERA_PREFIX) :]
        frames[camera][message.sequence] = (message.log_time, image.data)
