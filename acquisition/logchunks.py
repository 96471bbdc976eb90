"""A finished MCAP log read by its summary, chunk by chunk (acquisition/logreader.py).

mcap's own functions read the summary, the chunk records and their compressed data
(checked against the chunk's CRC); the records inside a decompressed chunk are walked by
their length fields here, and only the messages of the channels wanted are cut out: mcap's
``breakup_chunk`` makes a Python object and a stream read per field of every message and
its streaming reader parses the message-index records (one entry per message), which is
most of the time a replay took (benchmarks/bench_log.py). tests/test_log_fast.py holds
this to mcap's own readers.
"""

from __future__ import annotations

import io
import operator
import os
import pathlib
import struct
from typing import IO, Collection

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex
from mcap.stream_reader import get_chunk_data_stream
from mcap.writer import MCAP0_MAGIC

_RECORD_HEAD = struct.Struct("<BQ")        # MCAP record: opcode, content length
_MESSAGE_FIXED = 2 + 4 + 8 + 8
_MESSAGE_RECORD_HEAD = struct.Struct("<BQH4xQ")   # opcode, length, then the message's channel id, log time
_INDEX_HEAD = struct.Struct("<BQHI")       # MessageIndex: opcode, length, channel id, byte length of its entries
_INDEX_ENTRY = 16                          # (log time, offset)
_CHUNK_HEAD = struct.Struct("<BQQQQII")    # Chunk: opcode, length, start, end, uncompressed size, crc, name length


def chunk_messages(data: bytes, wanted: Collection[int] | None = None
                   ) -> tuple[int, dict[int, tuple[list[int], list[bytes]]]]:
    """The messages of a decompressed MCAP chunk: their number, and channel id ->
    (log times, payloads) in file order for the channels ``wanted`` (all when None).

    The records are walked by their length fields (docs: the MCAP specification's
    Chunk and Message records); the other records of a chunk (its Schema and
    Channel records, also in the summary) are stepped over. What mcap's
    ``breakup_chunk`` returns, without a Python object and a stream read per field
    of every message (tests/test_log_fast.py compares the two on every chunk)."""
    n = len(data)
    off = 0
    count = 0
    out: dict[int, tuple[list[int], list[bytes]]] = {}
    head, whole = _RECORD_HEAD.unpack_from, _MESSAGE_RECORD_HEAD.unpack_from
    whole_size, message_op, fixed, every = _MESSAGE_RECORD_HEAD.size, int(Opcode.MESSAGE), _MESSAGE_FIXED, wanted is None
    while off < n:
        if off + whole_size <= n:     # a message's head in one unpack (other records: their first bytes)
            opcode, length, channel, log_time = whole(data, off)
        else:
            (opcode, length), channel, log_time = head(data, off), None, None
        body = off + 9
        off = body + length
        if off > n:
            raise McapError(f"a record of {length} bytes runs past the end of its chunk")
        if opcode != message_op:
            continue
        if length < fixed:
            raise McapError(f"a message record of {length} bytes, shorter than its fixed fields")
        count += 1
        if not (every or channel in wanted):
            continue
        entry = out.get(channel)
        if entry is None:
            entry = out[channel] = ([], [])
        entry[0].append(log_time)
        entry[1].append(data[body + fixed:off])
    return count, out


def ends_with_magic(f: IO[bytes]) -> bool:
    """Whether the file ends with the MCAP closing magic (rewound to its start)."""
    f.seek(0, 2)
    size = f.tell()
    f.seek(max(size - len(MCAP0_MAGIC), 0))
    tail = f.read(len(MCAP0_MAGIC))
    f.seek(0)
    return size >= 2 * len(MCAP0_MAGIC) and tail == MCAP0_MAGIC


def indexed_chunks(path: str | pathlib.Path):
    """(chunk indexes in file order, mcap's summary) of a finished log whose every message is in
    an indexed chunk; None for any other file (truncated, no summary or statistics, messages
    outside chunks, a second log appended after it, unreadable), which is then streamed."""
    try:
        f = open(path, "rb")
    except OSError:
        return None             # the streaming reader names the error
    with f:
        try:
            if not ends_with_magic(f):
                return None
            size = os.fstat(f.fileno()).st_size
            summary = make_reader(f).get_summary()
            if summary is None or summary.statistics is None or not summary.chunk_indexes:
                return None
            if f.tell() != size - len(MCAP0_MAGIC):   # the footer read is not the file's last: a log appended
                return None
            chunks = sorted(summary.chunk_indexes, key=operator.attrgetter("chunk_start_offset"))
            if not all(_chunk_agrees(f, ci) for ci in chunks):
                return None
            in_chunks = 0
            for ci in chunks:            # the message indexes' entry counts, from their length fields
                for offset in ci.message_index_offsets.values():
                    f.seek(offset)
                    opcode, _, _, entries_len = _INDEX_HEAD.unpack(f.read(_INDEX_HEAD.size))
                    if opcode != Opcode.MESSAGE_INDEX:
                        return None
                    in_chunks += entries_len // _INDEX_ENTRY
            if in_chunks != summary.statistics.message_count:
                return None
        except (McapError, struct.error, EndOfFile, InvalidMagic, UnicodeDecodeError, OSError, ValueError):
            return None
    return chunks, summary


def _chunk_agrees(f: IO[bytes], ci: ChunkIndex) -> bool:
    """Whether the chunk record at ``ci`` has the lengths, sizes and compression its index
    gives (a corrupt length field sends the file to the streaming reader, which names it)."""
    f.seek(ci.chunk_start_offset)
    opcode, length, _, _, uncompressed, _, name_len = _CHUNK_HEAD.unpack(f.read(_CHUNK_HEAD.size))
    if opcode != Opcode.CHUNK or 9 + length != ci.chunk_length or uncompressed != ci.uncompressed_size:
        return False
    if f.read(name_len).decode("utf-8") != ci.compression:
        return False
    (records,) = struct.unpack("<Q", f.read(8))
    return records == ci.compressed_size and _CHUNK_HEAD.size + name_len + 8 + records == ci.chunk_length


def read_chunk(f: IO[bytes], index: ChunkIndex) -> bytes:
    """The decompressed records of the chunk at ``index`` (its CRC checked), as mcap's seeking
    reader reads it."""
    f.seek(index.chunk_start_offset + 1 + 8)
    chunk = Chunk.read(ReadDataStream(io.BytesIO(f.read(index.chunk_length - 9))))
    if len(chunk.data) != index.compressed_size:
        raise McapError(f"a chunk of {len(chunk.data)} compressed bytes, its index says {index.compressed_size}")
    stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    return stream.read(length) if length else b""
