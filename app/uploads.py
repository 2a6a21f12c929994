"""Loading an uploaded dump so that a malformed file is a 422 at its form field, not a 500."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from app.errors import RequestError

if TYPE_CHECKING:
    from calibrators import Dump


def load_upload(load: Callable[[], Dump], field: str) -> Dump:
    """Load an upload once so a malformed dump is a 422 now, not a failed job later.

    Every loader error is a 422 at `body.<field>`: the library's ValueErrors (FieldError
    included: its key is in the message) and, as a last resort, any other error a malformed
    file could still raise (MemoryError, RecursionError: the loaders refuse oversized and too
    deeply nested files before they get there).
    """
    try:
        return load()
    except ValueError as exc:
        reason = f"not a valid validation dump: {exc}"
    except (KeyError, TypeError, OverflowError, IndexError) as exc:
        reason = f"not a valid validation dump ({type(exc).__name__}): {exc}"
    except MemoryError:
        reason = "the dump is too large to load"
    except RecursionError:
        reason = "the dump is nested too deeply to load"
    except (OSError, EOFError) as exc:  # the stored copy is unreadable: no server path shown
        reason = f"the dump cannot be read: {getattr(exc, 'strerror', None) or type(exc).__name__}"
    raise RequestError(["body", field], reason)
