"""Ingest of whole recordings: the sensor file, ASTERIX (raw and pcap), plot tables (CSV,
Parquet), and the split of a recording into one :class:`solver.plots.PlotTable` per aircraft.
Pure computation (no web imports); formats in ``solver/io/README.md``."""

from .asterix import Recording, ServiceStats, read_recording
from .problems import Problem, Problems
from .sensors_file import SensorSet, load_sensors, parse_sensors
from .tables import PlotRows, read_table, unwrap_time_of_day, write_table

__all__ = ["PlotRows", "Problem", "Problems", "Recording", "SensorSet", "ServiceStats",
           "load_sensors", "parse_sensors", "read_recording", "read_table",
           "unwrap_time_of_day", "write_table"]
