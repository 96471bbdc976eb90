"""A readable copy of a killed log (``elastocal repair``).

A recorder killed mid-procedure leaves an MCAP file without its summary and
footer: elastocal's reader (:class:`~elastocal.acquisition.logreader.LogReader`)
reads it up to its last whole record, mcap's own ``make_reader`` does not.
:func:`repair_log` copies every whole record (header, schemas, channels,
messages with their times, metadata) into a new file that mcap's writer
finishes with its summary, so any MCAP tool opens it; nothing is invented and
the original is left as it is.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from elastocal.acquisition.logreader import LogReader
from elastocal.errors import InputError


@dataclass(frozen=True)
class Repaired:
    """What the copy holds and what the original lacked."""

    messages: int
    bytes_read: int          # of the original, up to its last whole record
    bytes_lost: int          # after it (the record the kill cut)
    was_complete: bool       # the original already had its summary


def repair_log(source: str | pathlib.Path, out: str | pathlib.Path) -> Repaired:
    """Copy the whole records of the log ``source`` into ``out``, finished with a summary."""
    reader = LogReader(source)
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    messages = 0
    with open(out, "wb") as f:
        writer: Writer | None = None
        for record in reader.records():
            if isinstance(record, Header):
                writer = Writer(f, compression=CompressionType.ZSTD)
                writer.start(profile=record.profile, library=record.library)
                continue
            if writer is None:
                raise InputError("the log does not start with an MCAP header", source=str(source))
            if isinstance(record, Schema) and record.id not in schemas:
                schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channels:
                channels[record.id] = writer.register_channel(record.topic, record.message_encoding,
                                                              schemas.get(record.schema_id, 0),
                                                              metadata=dict(record.metadata))
            elif isinstance(record, Message):
                if record.channel_id not in channels:
                    raise InputError(f"a message on channel {record.channel_id}, which the log never declared",
                                     source=str(source))
                writer.add_message(channels[record.channel_id], record.log_time, record.data,
                                   record.publish_time, record.sequence)
                messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                      record.data)
        if writer is None:
            raise InputError("empty file; not an MCAP log", source=str(source))
        writer.finish()
    size = pathlib.Path(source).stat().st_size
    read = reader.end_offset if not reader.complete else size
    return Repaired(messages=messages, bytes_read=read, bytes_lost=max(size - read, 0) if reader.truncated else 0,
                    was_complete=reader.complete)
