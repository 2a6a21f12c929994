"""The hostile Arrow bodies of issue 25, rebuilt: three bombs (compressed bodies that inflate
far past what they weigh) and the streams that crashed the server, echoed its memory or got
500s. Each builder takes the dump whose classes the served profile has."""

from __future__ import annotations

import struct

import numpy as np
import pyarrow as pa

from tests.arrow_mutator import buffer_roles, messages, request_batch, stream

GIB = 2**30


def _strings(rows: int, each: int) -> pa.Array:
    """`rows` strings of `each` NUL bytes, over a calloc'ed buffer that is never written (its
    pages stay unbacked: building a 1 GiB column costs this process little memory)."""
    offsets = pa.py_buffer((np.arange(rows + 1, dtype=np.int64) * each).astype(np.int32))
    data = pa.py_buffer(bytes(rows * each))
    return pa.Array.from_buffers(pa.string(), rows, [None, offsets, data])


def _with(batch: pa.RecordBatch, **columns: pa.Array) -> pa.RecordBatch:
    cols = {name: batch.column(name) for name in batch.schema.names}
    cols.update(columns)
    return pa.RecordBatch.from_pydict(cols)


def zstd_bomb(dump) -> bytes:
    """~100 KB of zstd that declares ~1 GiB: valid detections whose frame_ids are NUL bytes,
    1 GiB in all (the issue's 1,076,442,336-byte response)."""
    batch = request_batch(dump, 300)
    n = batch.num_rows
    return stream([_with(batch, frame_id=_strings(n, GIB // n))], "zstd")


def frame_id_bomb(dump, batches: int = 40) -> bytes:
    """`batches` one-row batches, each with a 16 MiB frame_id, zstd-compressed (~40 KB)."""
    one = request_batch(dump, 1)
    return stream([_with(one, frame_id=_strings(1, 16 * 2**20))] * batches, "zstd")


def rows_bomb(rows: int = 5_000_000) -> bytes:
    """`rows` detections of zeros in one zstd batch of a few tens of KB."""
    zeros = pa.array(np.zeros(rows, np.int8))
    batch = pa.RecordBatch.from_pydict({
        "frame_id": zeros, "score": pa.array(np.zeros(rows, np.float32)), "label": zeros,
        "box": pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(rows * 7, np.int8)), 7)})
    return stream([batch], "zstd")


def patched(data: bytes, schema: pa.Schema, column: str, role: str, *, at: int = 4,
            value: int, width: str = "<i", where: str = "body") -> bytes:
    """`data` with one field of the first batch's buffer (`column`, `role`) overwritten:
    the int at byte `at` of its body bytes (`where="body"`), or its length in the header
    (`where="length"`)."""
    out = bytearray(data)
    msg = next(m for m in messages(data) if m.kind == "record batch")
    i = buffer_roles(schema).index((column, role))
    offset, _ = msg.header.buffers[i]
    if where == "length":
        struct.pack_into("<q", out, msg.meta_at + msg.header.buffers_at + 16 * i + 8, value)
    else:
        struct.pack_into(width, out, msg.body_at + offset + at, value)
    return bytes(out)


def segfault(dump, rows: int = 60) -> bytes:
    """A `label` string column with an int32 offset patched to 0x7ffff000 (crashed the
    server: reading it walks far past the body); 3,000 rows make a ~500 KB body, the issue's
    variant that ran in a worker thread."""
    batch = request_batch(dump, rows, variant=1)
    return patched(stream([batch]), batch.schema, "label", "offsets", at=4 * (rows // 2),
                   value=0x7FFFF000)


def echo_leak(dump) -> bytes:
    """A `frame_id` column whose last offset points past its data (was echoed in a 200
    carrying bytes the server never received)."""
    batch = request_batch(dump, 60)
    return patched(stream([batch]), batch.schema, "frame_id", "offsets", at=4 * 60,
                   value=4096)


def zero_rows(dump) -> bytes:
    """A valid schema with one zero-row batch (was `ValueError: cannot reshape`)."""
    return stream([request_batch(dump, 5).slice(0, 0)])


def dictionary_index(dump) -> bytes:
    """A dictionary `label` with index 1,000,000 (was ArrowIndexError)."""
    batch = request_batch(dump, 20, variant=2)
    return patched(stream([batch]), batch.schema, "label", "indices", at=0, value=1_000_000)


def zstd_prefix(dump) -> bytes:
    """A zstd stream whose `logits` buffer declares -1 as its uncompressed length (was
    ArrowInvalid): -1 means "stored as is", so its zstd bytes are read as raw floats."""
    batch = request_batch(dump, 200)
    return patched(stream([batch], "zstd"), batch.schema, "logits", "data", at=0, value=-1,
                   width="<q")


def short_id(dump) -> bytes:
    """2,000 detections whose int64 `id` buffer length is patched from 16,000 to 8."""
    batch = request_batch(dump, 2_000)
    assert batch.num_rows == 2_000, "the dump needs 2,000 detections"
    return patched(stream([batch]), batch.schema, "id", "data", value=8, where="length")


def heavy_valid(dump, rows: int = 20_000, layers: int = 38) -> bytes:
    """A valid zstd request of ~1.8 MB that decodes to ~60 MiB (layer_logits `[layers][C]`),
    just under the 64 MiB cap: accepted, and seconds of work that must stay off the event
    loop."""
    batch = request_batch(dump, rows)
    logits = batch.column("logits").flatten().to_numpy().reshape(rows, 1, -1)
    per_layer = np.repeat(logits, layers, axis=1)
    inner = pa.FixedSizeListArray.from_arrays(pa.array(per_layer.reshape(-1)),
                                              per_layer.shape[-1])
    cols = {name: batch.column(name) for name in batch.schema.names if name != "logits"}
    cols["layer_logits"] = pa.FixedSizeListArray.from_arrays(inner, layers)
    return stream([pa.RecordBatch.from_pydict(cols)], "zstd")
