"""Structured logs: one JSON object per line on stderr."""

from __future__ import annotations

import json
import logging
import time

LOGGER = logging.getLogger("service")


MAX_FIELD_CHARS = 4000  # a longer string field (a traceback, an error list) is cut to this


def _bounded(value: object) -> object:
    if isinstance(value, str) and len(value) > MAX_FIELD_CHARS:
        return f"{value[:MAX_FIELD_CHARS // 2]} ...[{len(value) - MAX_FIELD_CHARS} chars cut]... " \
               f"{value[-MAX_FIELD_CHARS // 2:]}"
    return value


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "msg", **extra}``; ``extra`` comes from ``log(..., extra=)``
    under the key ``fields``. Every string is cut to :data:`MAX_FIELD_CHARS` (its head and
    tail), so no single request can write megabytes of log."""

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        out.update(getattr(record, "fields", {}))
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps({k: _bounded(v) for k, v in out.items()}, default=str)


def setup_logging(level: str) -> None:
    """JSON lines on stderr for the service's logger, uvicorn's, and every other (the root
    logger: the solver's warnings, in the server and in each worker process)."""
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter())
    for name in ("service", "uvicorn", "uvicorn.error"):
        log = logging.getLogger(name)
        log.handlers[:] = [handler]
        log.setLevel(level)
        log.propagate = False
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    logging.captureWarnings(True)  # Python warnings as JSON lines too, not plain text
