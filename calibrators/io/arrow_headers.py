"""What an Arrow IPC record batch message says about itself before its body is decoded: its
row count, its field nodes, where its buffers lie in the body and whether they are
compressed (`arrow_safe` caps rows and inflated bytes from these, batch by batch).

The metadata of an IPC message is a flatbuffer (`Message.fbs` of the Arrow format): a root
offset, then tables that reach their fields through a vtable. Only the fields below are read,
every position is bounds-checked, and anything malformed is a `ValueError`: a hostile header
costs a few Python comparisons, never an allocation sized by the client.

    Message      { version: short, header_type: ubyte, header: union, bodyLength: long, ... }
    RecordBatch  { length: long, nodes: [FieldNode], buffers: [Buffer],
                   compression: BodyCompression, ... }
    DictionaryBatch { id: long, data: RecordBatch, isDelta: bool }
    FieldNode    struct { length: long, null_count: long }     (16 bytes)
    Buffer       struct { offset: long, length: long }         (16 bytes)
    BodyCompression { codec: byte (0 LZ4_FRAME, 1 ZSTD), method: byte }

The `*_at` positions (offsets into the metadata bytes) let a test patch a header in place.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

CODECS = {0: "lz4_frame", 1: "zstd"}
_MESSAGE_HEADER = 2          # field index of Message.header (header_type is 1)
_RECORD_BATCH, _DICTIONARY_BATCH = 3, 2   # MessageHeader union tags


@dataclass(frozen=True)
class BatchHeader:
    """The header of one record batch message.

    rows: the batch's length; nodes: `(length, null_count)` per field node, depth first;
    buffers: `(offset, length)` of each buffer in the body; codec: None when the buffers are
    stored as is, else a name of `CODECS` (every buffer then starts with its int64 inflated
    length, -1 meaning "stored as is"). rows_at, nodes_at, buffers_at: where `length` and the
    first node and buffer structs lie in the metadata."""

    rows: int
    nodes: tuple[tuple[int, int], ...]
    buffers: tuple[tuple[int, int], ...]
    codec: str | None
    rows_at: int
    nodes_at: int
    buffers_at: int


def batch_header(metadata: bytes | memoryview) -> BatchHeader:
    """The header of a record batch (or dictionary batch) message from its flatbuffer
    `metadata`; ValueError when it is malformed or is another kind of message."""
    buf = memoryview(metadata).cast("B")
    message = _root(buf)
    kind = _scalar(buf, message, 1, "B", 0)
    header = _table(buf, message, _MESSAGE_HEADER)
    if header is None:
        raise ValueError("the message has no header")
    if kind == _DICTIONARY_BATCH:
        header = _table(buf, header, 1)
        if header is None:
            raise ValueError("the dictionary batch has no data")
    elif kind != _RECORD_BATCH:
        raise ValueError(f"message header type {kind} is not a record batch")
    rows_at = _field_at(buf, header, 0)
    rows = _read(buf, rows_at, "<q") if rows_at else 0
    nodes_at, nodes = _structs(buf, header, 1)
    buffers_at, buffers = _structs(buf, header, 2)
    codec = None
    compression = _table(buf, header, 3)
    if compression is not None:
        code = _scalar(buf, compression, 0, "b", 0)
        if code not in CODECS:
            raise ValueError(f"unknown compression codec {code}")
        if _scalar(buf, compression, 1, "b", 0) != 0:
            raise ValueError("unknown body compression method")
        codec = CODECS[code]
    if rows < 0 or any(n < 0 or c < 0 for n, c in nodes):
        raise ValueError("negative row or null count in the batch header")
    return BatchHeader(rows, nodes, buffers, codec, rows_at, nodes_at, buffers_at)


def inflated_bytes(header: BatchHeader, body: bytes | memoryview) -> int:
    """Bytes the batch's buffers take once decoded: their lengths, or for a compressed body
    the int64 length each buffer declares ahead of its compressed bytes (read, not
    inflated); ValueError for a buffer outside the body or a negative declared length."""
    view = memoryview(body).cast("B")
    total = 0
    for offset, length in header.buffers:
        if offset < 0 or length < 0 or offset + length > len(view):
            raise ValueError(f"buffer ({offset}, {length}) lies outside the {len(view)}-byte "
                             f"body")
        if header.codec is None or length == 0:
            total += length
            continue
        if length < 8:
            raise ValueError(f"compressed buffer of {length} bytes has no length prefix")
        declared = _read(view, offset, "<q")
        if declared == -1:
            total += length - 8
        elif declared < 0:
            raise ValueError(f"compressed buffer declares {declared} bytes")
        else:
            total += declared
    return total


# -- flatbuffer access --------------------------------------------------------------------


def _read(buf: memoryview, pos: int, fmt: str) -> int:
    size = struct.calcsize(fmt)
    if pos < 0 or pos + size > len(buf):
        raise ValueError(f"flatbuffer read at {pos} outside {len(buf)} bytes")
    return struct.unpack_from(fmt, buf, pos)[0]


def _root(buf: memoryview) -> int:
    return _read(buf, 0, "<I")


def _field_at(buf: memoryview, table: int, index: int) -> int:
    """Position of field `index` of the table at `table`, 0 when absent."""
    vtable = table - _read(buf, table, "<i")
    vsize = _read(buf, vtable, "<H")
    slot = 4 + 2 * index
    if slot + 2 > vsize:
        return 0
    offset = _read(buf, vtable + slot, "<H")
    return table + offset if offset else 0


def _scalar(buf: memoryview, table: int, index: int, fmt: str, default: int) -> int:
    at = _field_at(buf, table, index)
    return _read(buf, at, "<" + fmt) if at else default


def _table(buf: memoryview, table: int, index: int) -> int | None:
    at = _field_at(buf, table, index)
    return at + _read(buf, at, "<I") if at else None


def _structs(buf: memoryview, table: int, index: int) -> tuple[int, tuple[tuple[int, int], ...]]:
    """(position of the first element, elements) of a vector of 16-byte (long, long) structs."""
    at = _field_at(buf, table, index)
    if not at:
        return 0, ()
    vector = at + _read(buf, at, "<I")
    count = _read(buf, vector, "<I")
    start = vector + 4
    if start + 16 * count > len(buf):
        raise ValueError(f"a vector of {count} structs overruns the metadata")
    pairs = np.frombuffer(buf, "<i8", count=2 * count, offset=start).reshape(count, 2)
    return start, tuple(map(tuple, pairs.tolist()))
