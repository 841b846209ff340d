"""Dask worker plugins of the service's embedded job cluster (imported with Dask, when the
first job starts it)."""

from __future__ import annotations

import os
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin


class Niceness(WorkerPlugin):
    """Lowers its worker process's CPU priority by ``n`` at its start (each worker started
    later, e.g. after a killed one, too): the jobs' tracks yield to single-track requests."""

    name = "trajrecon-niceness"

    def __init__(self, n: int):
        self.n = n

    def setup(self, worker: Any) -> None:
        os.nice(self.n)
