"""Structured logs: one JSON object per line on stderr."""

from __future__ import annotations

import json
import logging
import time

LOGGER = logging.getLogger("service")


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "msg", **extra}``; ``extra`` comes from ``log(..., extra=)``
    under the key ``fields``."""

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
        return json.dumps(out, default=str)


def setup_logging(level: str) -> None:
    """JSON lines on stderr for the service's logger and uvicorn's error logger."""
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter())
    for name in ("service", "uvicorn", "uvicorn.error"):
        log = logging.getLogger(name)
        log.handlers[:] = [handler]
        log.setLevel(level)
        log.propagate = False
