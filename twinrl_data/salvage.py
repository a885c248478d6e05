"""Episode files that a crash cut short or a disk damaged: salvage and checks.

- :func:`recover` rewrites what is intact of an episode file into a new, valid one: a
  killed recorder's file up to its last closed chunk, a damaged file without its
  damaged chunks (each lost span is reported).
- :func:`check_episode_file` reads a file the way ``git fsck`` reads objects: every
  chunk's and the data section's checksum, every message and camera frame decoded.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from twinrl_data import mcap_log
from twinrl_data.atomic import write_atomic
from twinrl_data.errors import McapError


@dataclass(frozen=True)
class Recovery:
    """What :func:`recover` kept."""

    source: Path
    output: Path
    messages: int
    metadata: int
    complete: bool  # the source was already a valid, finished, undamaged file
    lost_spans: list[tuple[int, int]] = field(default_factory=list)  # log times (ns)


@dataclass
class _Salvaged:
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)
    lost_spans: list[tuple[int, int]] = field(default_factory=list)
    finished: bool = False


def _salvage(path: Path) -> _Salvaged:
    """Every intact record of ``path``; a chunk whose checksum fails is skipped whole."""
    kept = _Salvaged()

    def keep(record: object) -> None:
        if isinstance(record, Schema):
            kept.schemas[record.id] = record
        elif isinstance(record, Channel):
            kept.channels[record.id] = record
        elif isinstance(record, Message):
            kept.messages.append(record)
        elif isinstance(record, Metadata):
            kept.metadata.append(record)

    def skip(chunk: Chunk) -> None:
        kept.lost_spans.append((chunk.message_start_time, chunk.message_end_time))

    with open(path, "rb") as f:
        try:
            for record in mcap_log.intact_records(f, skip):
                keep(record)
                kept.finished |= isinstance(record, Footer)
        except Exception:
            # A cut or damaged record ends the reading (the records after it cannot be
            # found); everything before it is kept.
            kept.finished = False
    return kept


def recover(path: str | Path, output: str | Path | None = None, *, force: bool = False) -> Recovery:
    """Rewrite the intact part of an episode log (e.g. from a killed recorder, or with a
    damaged chunk) into a valid file.

    Every intact record is kept. ``output`` defaults to ``<name>.recovered.mcap`` beside
    the source; it is not overwritten unless ``force``.
    """
    path = Path(path)
    if path.is_dir():
        raise McapError(f"{path} is a folder; give an episode .mcap file")
    mcap_log.read_summary(path)  # refuses what is not an episode log, naming why
    output = Path(output) if output is not None else path.with_suffix(".recovered.mcap")
    if output.resolve() == path.resolve():
        raise McapError("recover writes a new file; choose an `output` other than the damaged file")
    if output.exists() and not force:
        raise McapError(
            f"{output} already exists; choose another `output` or overwrite it (`force`)"
        )
    kept = _salvage(path)
    messages = [
        m
        for m in kept.messages
        if m.channel_id in kept.channels and kept.channels[m.channel_id].schema_id in kept.schemas
    ]
    buffer = io.BytesIO()
    writer = Writer(buffer, compression=CompressionType.ZSTD, enable_data_crcs=True)
    writer.start(profile="twinrl", library=mcap_log.RECOVERED_BY)
    schema_ids = {
        old: writer.register_schema(s.name, s.encoding, s.data) for old, s in kept.schemas.items()
    }
    channel_ids = {
        old: writer.register_channel(
            c.topic, c.message_encoding, schema_ids[c.schema_id], c.metadata
        )
        for old, c in kept.channels.items()
        if c.schema_id in schema_ids
    }
    for m in messages:
        writer.add_message(
            channel_ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence
        )
    for record in kept.metadata:
        writer.add_metadata(record.name, record.metadata)
    writer.finish()
    write_atomic(output, buffer.getvalue())
    return Recovery(
        source=path,
        output=output,
        messages=len(messages),
        metadata=len(kept.metadata),
        complete=kept.finished and not kept.lost_spans,
        lost_spans=kept.lost_spans,
    )


def check_episode_file(path: str | Path) -> list[str]:
    """Problems of one episode file, one line each (none: every byte checks out).

    The file must be an episode log that its recorder finished (start and end records),
    every chunk's checksum and the data section's must match, and every message and
    camera frame must decode (the whole episode is read as :func:`read_episode` reads it).
    """
    path = Path(path)
    try:
        summary = mcap_log.read_summary(path)
    except McapError as err:
        return [str(err)]
    if summary.length is None:
        return [f"{path} was never finished (its recorder stopped): recover it"]
    try:
        episode = mcap_log.read_episode(path)
    except McapError as err:
        return [str(err)]
    if len(episode) != summary.length:
        return [f"{path} holds {len(episode)} whole steps, its end record says {summary.length}"]
    return []
