"""Ingest of whole recordings: the sensor file, ASTERIX (raw and pcap), plot tables (CSV,
Parquet), the split of a recording into one :class:`solver.plots.PlotTable` per aircraft, and
a recording read so for a run, whole or as it goes (:mod:`solver.io.reading`).
Pure computation (no web imports); formats in ``solver/io/README.md``.

The ASTERIX names are imported on first use: libasterix's generated specifications take over a
second to import, which users of the tables alone need not pay."""

from __future__ import annotations

from typing import Any

from .problems import Problem, Problems
from .sensors_file import SensorSet, load_sensors, parse_sensors
from .tables import PlotRows, iter_table, read_table, unwrap_time_of_day, write_table

_LAZY = {"Recording", "ServiceStats", "read_recording", "iter_recording", "encode_rows"}

__all__ = ["PlotRows", "Problem", "Problems", "Recording", "SensorSet", "ServiceStats",
           "encode_rows", "iter_recording", "iter_table", "load_sensors", "parse_sensors",
           "read_recording", "read_table", "unwrap_time_of_day", "write_table"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from . import asterix

        return getattr(asterix, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
