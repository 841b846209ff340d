"""``python -m service``: serve ``service.app:app`` with uvicorn on the configured host/port."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence

from pydantic import ValidationError

from .logs import setup_logging
from .server import serve
from .settings import get_settings

OPTIONS = {"host": str, "port": int, "workers": int, "data_dir": str, "dask_scheduler": str}
"""Settings the command line may set (each also ``TRAJRECON_<NAME>``; the option wins)."""


def main(argv: Sequence[str] | None = None) -> None:
    """Run one uvicorn process; the solves run in its worker pool (``TRAJRECON_WORKERS``).
    Logging is set up before uvicorn starts, so every line, the first included, is JSON.
    The options are put in the environment before the settings are first read, so the app
    (loaded by uvicorn by name) reads the same."""
    parser = argparse.ArgumentParser(
        prog="python -m service", description="Serve the reconstruction API. Every setting is "
        "read from a TRAJRECON_<NAME> environment variable (README); these options set some "
        "of them for this run.")
    for name, kind in OPTIONS.items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, default=None,
                            help=f"as TRAJRECON_{name.upper()}")
    args = parser.parse_args(argv)
    for name in OPTIONS:
        value = getattr(args, name)
        if value is not None:
            os.environ[f"TRAJRECON_{name.upper()}"] = str(value)
    get_settings.cache_clear()
    try:
        s = get_settings()
    except ValidationError as e:  # a bad option or variable: argparse's usage error, exit 2
        parser.error("; ".join(f"TRAJRECON_{'_'.join(map(str, err['loc'])).upper()}: "
                               f"{err['msg']}" for err in e.errors()))
    setup_logging(s.log_level)
    serve(s)


if __name__ == "__main__":
    main()
