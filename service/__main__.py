"""``python -m service``: serve ``service.app:app`` with uvicorn on the configured host/port."""

from __future__ import annotations

from .logs import setup_logging
from .server import serve
from .settings import get_settings


def main() -> None:
    """Run one uvicorn process; the solves run in its worker pool (``TRAJRECON_WORKERS``).
    Logging is set up before uvicorn starts, so every line, the first included, is JSON."""
    s = get_settings()
    setup_logging(s.log_level)
    serve(s)


if __name__ == "__main__":
    main()
