"""The server's log: the `detcal.*` loggers (fit jobs, activations, refusals, feedback alarms,
connections) and uvicorn's own, on stderr, at `detcal serve --log-level`, as text lines or JSON
lines (`DETCAL_LOG_FORMAT=json`). A filter on every handler replaces the configured tokens
with `<token>`, should one ever reach a message: the log never carries a token."""

from __future__ import annotations

import json
import logging
from datetime import UTC, datetime
from typing import Any

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class JsonLinesFormatter(logging.Formatter):
    """One JSON object per record: `time` (UTC, ISO 8601), `level`, `logger`, `message`,
    and `exception` when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname, "logger": record.name, "message": record.getMessage()}
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        return json.dumps(line, ensure_ascii=False)


class RedactTokens(logging.Filter):
    """Replace the admin and feedback tokens of the process's settings in a record's message."""

    def __init__(self) -> None:
        super().__init__()
        from app.settings import get_settings

        s = get_settings()
        self.secrets = [t.get_secret_value() for t in (s.admin_token, s.feedback_token)
                        if t is not None and t.get_secret_value()]

    def filter(self, record: logging.LogRecord) -> bool:
        if self.secrets:
            message = record.getMessage()
            if any(secret in message for secret in self.secrets):
                for secret in self.secrets:
                    message = message.replace(secret, "<token>")
                record.msg, record.args = message, None
        return True


def log_config(level: str = "info", fmt: str = "text") -> dict[str, Any]:
    """A `logging.config.dictConfig` (uvicorn's `log_config`) sending `detcal.*` and uvicorn's
    loggers to stderr at `level`, as `fmt` (`text` or `json`) lines."""
    formatter = ({"()": "app.http.logs.JsonLinesFormatter"} if fmt == "json"
                 else {"format": TEXT_FORMAT})
    handler = {"class": "logging.StreamHandler", "stream": "ext://sys.stderr",
               "formatter": "line", "filters": ["redact"]}
    upper = level.upper()
    return {
        "version": 1, "disable_existing_loggers": False,
        "filters": {"redact": {"()": "app.http.logs.RedactTokens"}},
        "formatters": {"line": formatter},
        "handlers": {"stderr": handler},
        "loggers": {
            "detcal": {"handlers": ["stderr"], "level": upper, "propagate": False},
            "uvicorn": {"handlers": ["stderr"], "level": upper, "propagate": False},
            "uvicorn.error": {"level": upper},
            "uvicorn.access": {"handlers": ["stderr"], "level": upper, "propagate": False},
        },
    }
