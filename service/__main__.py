"""``python -m service``: serve ``service.app:app`` with uvicorn on the configured host/port."""

from __future__ import annotations

import uvicorn

from .logs import setup_logging
from .settings import get_settings


def main() -> None:
    """Run one uvicorn process; the solves run in its worker pool (``TRAJRECON_WORKERS``)."""
    s = get_settings()
    setup_logging(s.log_level)
    uvicorn.run("service.app:app", host=s.host, port=s.port, log_level=s.log_level.lower(),
                log_config=None, access_log=False, proxy_headers=True)


if __name__ == "__main__":
    main()
