"""A bounded, validating reader of Arrow IPC streams sent by clients (the body of an Arrow
calibrate request): hostile bytes become a `FieldError`, never a crash, a memory bomb or
memory of this process in a response.

The stream is read message by message (`pa.ipc.MessageReader`). Before a record batch is
decoded its header (`arrow_headers.batch_header`) is checked: the rows of all batches so far
against `max_rows`, and the bytes its buffers take once decoded (compressed buffers: the
length each declares, read without inflating) against `max_bytes`, so no batch past either
cap is ever decompressed. Compression (LZ4 frame, ZSTD) is accepted within `max_bytes`.
Every decoded batch is validated in full (`RecordBatch.validate(full=True)`: offsets, lengths,
UTF-8) before any column is read. The schema allows numbers (integer or float), strings, and
lists or structs of them (nested at most two deep); dictionary-encoded and other columns are
refused by name. The identity columns echoed back (`frame_id`, `id`) are copied out of the validated
batch, and their strings capped at `MAX_ID_BYTES`.

Failures name the column when one is at fault (`FieldError(column)`), else the body
(`FieldError("body")`); `FieldError("rows")` and `FieldError("bytes")` are the two caps.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from calibrators.core.errors import FieldError
from calibrators.io.arrow_headers import batch_header, inflated_bytes

#: Bytes an Arrow body may take once decoded (all batches, compressed buffers inflated).
MAX_INFLATED_BYTES = 64 * 2**20
#: Record batches one stream may hold.
MAX_BATCHES = 1024
#: Bytes of one string of an echoed identity column (`frame_id`, `id`).
MAX_ID_BYTES = 256
IDENTITY_COLUMNS = ("frame_id", "id")
_NESTING = 2


def read_safe_stream(data: bytes, max_rows: int | None = None,
                     max_bytes: int = MAX_INFLATED_BYTES) -> pa.RecordBatch:
    """The record batches of the Arrow IPC stream `data` as one validated batch with at least
    one row, its identity columns copied and capped (module docstring); FieldError otherwise."""
    try:
        reader = pa.ipc.MessageReader.open_stream(pa.BufferReader(data))
        first = reader.read_next_message()
        if first.type != "schema":
            raise ValueError(f"the stream starts with a {first.type} message, not a schema")
        schema = pa.ipc.read_schema(first)
        names = [field.name for field in schema]   # UnicodeDecodeError: not UTF-8
    except FieldError:
        raise
    except (StopIteration, ValueError, pa.ArrowException, OSError) as exc:
        raise FieldError("body", f"not an Arrow IPC stream: {_text(exc)}") from None
    if len(set(names)) != len(names):
        raise FieldError("body", f"repeated column names: {names}")
    check_schema(schema)
    batches, rows, inflated, count = [], 0, 0, 0
    while True:
        try:
            message = reader.read_next_message()
        except StopIteration:
            break
        except (ValueError, pa.ArrowException, OSError) as exc:
            raise FieldError("body", f"not an Arrow IPC stream: {_text(exc)}") from None
        count += 1
        if count > MAX_BATCHES:
            raise FieldError("body", f"the stream holds more than {MAX_BATCHES} record batches")
        if message.type != "record batch":
            raise FieldError("body", f"unexpected {message.type} message (dictionary batches "
                                     f"are not accepted)")
        try:
            header = batch_header(message.metadata)
            size = inflated_bytes(header, message.body if message.body is not None else b"")
        except ValueError as exc:
            raise FieldError("body", f"record batch {count - 1}: bad header: {exc}") from None
        rows, inflated = rows + header.rows, inflated + size
        if max_rows is not None and rows > max_rows:
            raise FieldError("rows", f"the batch has {rows} rows (detections); at most "
                                     f"{max_rows} are calibrated per request")
        if inflated > max_bytes:
            raise FieldError("bytes", f"the stream's batches take {inflated} bytes (or more) "
                                      f"once decoded; at most {max_bytes} are read per "
                                      f"request")
        batch = _decoded(first, message, schema, count - 1)
        for name in IDENTITY_COLUMNS:   # before the next batch inflates
            if name in names:
                _check_identity(name, batch.column(name), rows - batch.num_rows)
        if batch.num_rows:
            batches.append(batch)
    if not batches:
        raise FieldError("body", "the Arrow stream holds no rows (detections)")
    return _with_identity_copied(batches, schema)


def plain_stream(data: bytes, max_messages: int = 16) -> bool:
    """Whether `data` is an Arrow stream of at most `max_messages` messages whose record
    batches are all stored uncompressed (read from the message headers only): such a body
    decodes to at most its own size, in a few steps."""
    try:
        reader = pa.ipc.MessageReader.open_stream(pa.BufferReader(data))
        for i, message in enumerate(reader):
            if i >= max_messages or message.type == "dictionary":
                return False
            if message.type == "record batch" and batch_header(message.metadata).codec:
                return False
    except (ValueError, pa.ArrowException, OSError):
        return False
    return True


def check_schema(schema: pa.Schema) -> None:
    """FieldError(column) for a column whose type is not numbers, strings, or lists or structs
    of them nested at most `_NESTING` deep (dictionary-encoded columns included)."""
    for field in schema:
        bad = _bad_type(field.type, _NESTING)
        if bad is None:
            continue
        if pa.types.is_dictionary(bad):
            raise FieldError(field.name, f"column {field.name!r} is dictionary-encoded "
                                         f"({field.type}); send its values "
                                         f"({bad.value_type}) instead")
        raise FieldError(field.name, f"column {field.name!r} has type {field.type}; columns "
                                     f"hold numbers, strings, or lists or structs of them "
                                     f"(at most {_NESTING} deep)")


def _bad_type(kind: pa.DataType, depth: int) -> pa.DataType | None:
    """The first type within `kind` that is not accepted, or None."""
    if (pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_string(kind)
            or pa.types.is_large_string(kind)):
        return None
    if depth > 0 and _is_list(kind):
        return _bad_type(kind.value_type, depth - 1)
    if depth > 0 and pa.types.is_struct(kind):
        for i in range(kind.num_fields):
            bad = _bad_type(kind.field(i).type, depth - 1)
            if bad is not None:
                return bad
        return None
    return kind


def _decoded(schema_message: pa.ipc.Message, message: pa.ipc.Message, schema: pa.Schema,
             index: int) -> pa.RecordBatch:
    """Batch `index` decoded and validated in full; FieldError naming the first column that
    does not decode or validate on its own (or the body)."""
    try:
        batch = pa.ipc.read_record_batch(message, schema)
        batch.validate(full=True)
        return batch
    except (ValueError, pa.ArrowException, OSError) as exc:
        reason = _text(exc)
    column = _column_at_fault(schema_message, message, schema)
    raise FieldError(column or "body", f"record batch {index} is invalid"
                                       f"{f' in column {column!r}' if column else ''}: {reason}")


def _column_at_fault(schema_message: pa.ipc.Message, message: pa.ipc.Message,
                     schema: pa.Schema) -> str | None:
    """The first column that fails to decode or validate when read alone (an error path)."""
    stream = schema_message.serialize().to_pybytes() + message.serialize().to_pybytes()
    for i, field in enumerate(schema):
        options = pa.ipc.IpcReadOptions(included_fields=[i], use_threads=False)
        try:
            with pa.ipc.open_stream(stream, options=options) as reader:
                reader.read_next_batch().validate(full=True)
        except (ValueError, pa.ArrowException, OSError):
            return field.name
    return None


def _with_identity_copied(batches: list[pa.RecordBatch], schema: pa.Schema) -> pa.RecordBatch:
    """One batch of the validated `batches`, its identity columns fresh copies of their
    values (never the client's buffers) and their strings at most MAX_ID_BYTES long."""
    if len(batches) == 1:
        batch = batches[0]
    else:
        table = pa.Table.from_batches(batches, schema=schema).combine_chunks()
        batch = table.to_batches()[0]
    arrays = list(batch.columns)
    for i, name in enumerate(batch.schema.names):
        if name in IDENTITY_COLUMNS:   # a copy of the values, not the client's buffers
            arrays[i] = pc.take(arrays[i], pa.array(np.arange(len(arrays[i]), dtype=np.int64)))
    return pa.RecordBatch.from_arrays(arrays, schema=batch.schema)


def _check_identity(name: str, arr: pa.Array, first_row: int) -> None:
    """FieldError(name, row) for a string of identity column `arr` (a validated batch whose
    first row is request row `first_row`) over MAX_ID_BYTES, the row given for a column of
    plain strings; FieldError(name) for a column whose buffers take more than MAX_ID_BYTES
    (plus offsets and validity) per row (lists: an echo must not amplify the body)."""
    for flat in _strings(arr):
        if not len(flat):
            continue
        lengths = pc.binary_length(flat)
        longest = pc.max(lengths).as_py()
        if longest is not None and longest > MAX_ID_BYTES:
            row = int(pc.index(pc.greater(lengths, MAX_ID_BYTES), True).as_py()) + first_row
            row = row if flat is arr else None
            raise FieldError(name, f"{name} strings hold at most {MAX_ID_BYTES} bytes; got "
                                   f"{longest}{'' if row is None else f' at row {row}'}",
                             row=row)
    size = arr.nbytes   # the bytes its rows use
    if len(arr) and size > (MAX_ID_BYTES + 16) * len(arr):
        raise FieldError(name, f"{name} takes {size} bytes for {len(arr)} rows; its values "
                               f"hold at most {MAX_ID_BYTES} bytes each")


def _strings(arr: pa.Array) -> list[pa.Array]:
    """The string arrays within `arr` (itself, or the leaves of its lists and structs)."""
    if pa.types.is_string(arr.type) or pa.types.is_large_string(arr.type):
        return [arr]
    if _is_list(arr.type):
        return _strings(arr.flatten())
    if pa.types.is_struct(arr.type):
        return [s for child in arr.flatten() for s in _strings(child)]
    return []


def _is_list(kind: pa.DataType) -> bool:
    return (pa.types.is_list(kind) or pa.types.is_large_list(kind)
            or pa.types.is_fixed_size_list(kind))


def _text(exc: BaseException) -> str:
    """An exception's message, short (pyarrow's can quote a whole buffer)."""
    text = str(exc) or type(exc).__name__
    return text if len(text) <= 300 else text[:297] + "..."
