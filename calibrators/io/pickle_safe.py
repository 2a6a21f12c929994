"""A restricted unpickler: numpy arrays and plain containers, nothing else.

`pickle.load` runs whatever callable a pickle names (`os.system`, `builtins.eval`, ...), so
detcal never calls it. `load_restricted` reads a pickle whose globals are only those numpy
needs to rebuild arrays, dtypes and scalars; plain containers (dict, list, tuple, str, bytes,
int, float, bool, None) need no global. Any other global is refused before it is looked up,
naming it. For the offline readers only (`detcal convert`): the service never reads pickles.
"""

from __future__ import annotations

import io
import pickle

from calibrators.core.errors import FieldError

#: (module, name) a pickle may name: numpy's array, dtype and scalar reconstruction (both the
#: numpy 1.x `numpy.core` and the numpy 2.x `numpy._core` paths), and set types. Protocol-2
#: pickles also name `_codecs.encode` and `__builtin__.bytes` for bytes: they are replaced by a
#: latin-1-only encoder and a `bytes` that takes no size.
ALLOWED_GLOBALS = frozenset({
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("builtins", "set"), ("builtins", "frozenset"),
})


def _latin1(text: str, encoding: str = "latin1") -> bytes:
    """`_codecs.encode` as protocol-2 pickles use it for bytes: latin-1 only."""
    if encoding not in ("latin1", "latin-1") or not isinstance(text, str):
        raise pickle.UnpicklingError(f"it calls _codecs.encode with {encoding!r}; only latin1 "
                                     "(bytes in protocol 2) is allowed")
    return text.encode("latin1")


def _bytes(*args: object) -> bytes:
    """`bytes` as protocol-2 pickles use it (`bytes()`, `bytes(list)`), never `bytes(n)`."""
    if args and not isinstance(args[0], list | bytes):
        raise pickle.UnpicklingError("it calls bytes() with a size; only bytes(list) is "
                                     "allowed")
    return bytes(*args)  # type: ignore[arg-type]


class RestrictedUnpickler(pickle.Unpickler):
    """`pickle.Unpickler` whose `find_class` allows only `ALLOWED_GLOBALS`."""

    def find_class(self, module: str, name: str) -> object:
        module = "builtins" if module == "__builtin__" else module  # protocol 2 spelling
        if (module, name) == ("_codecs", "encode"):
            return _latin1
        if (module, name) == ("builtins", "bytes"):
            return _bytes
        if (module, name) not in ALLOWED_GLOBALS:
            raise pickle.UnpicklingError(f"it names {module}.{name}, which is not allowed: only "
                                         "numpy arrays and plain containers are read")
        return super().find_class(module, name)

    def persistent_load(self, pid: object) -> object:
        raise pickle.UnpicklingError("it uses persistent ids, which are not allowed")


def load_restricted(data: bytes, name: str) -> object:
    """The object of the pickle `data` (from the file called `name`), or a FieldError naming
    the file and the reason (a refused global, a truncated or corrupt pickle)."""
    try:
        return RestrictedUnpickler(io.BytesIO(data)).load()
    except pickle.UnpicklingError as exc:
        raise FieldError("pickle", f"{name}: not read: {exc}") from None
    except EOFError:
        raise FieldError("pickle", f"{name}: the pickle is truncated (ends before its STOP "
                                   "opcode)") from None
    except Exception as exc:  # noqa: BLE001  corrupt input breaks the C unpickler in any way
        raise FieldError("pickle", f"{name}: not a readable pickle of arrays and containers: "
                                   f"{type(exc).__name__}: {str(exc)[:120]}") from None
