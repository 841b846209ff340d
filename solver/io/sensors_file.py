"""The sensor file a user supplies with a recording (JSON).

Either a list of sensor objects, or an object ``{"sensors": [...], "reference": {"lat_deg",
"lon_deg"}}`` whose optional ``reference`` is the tangent point of the recording's plane (every
track is reconstructed in it). Sensor objects are those of ``../shared/spec/sensors.md`` plus
``"sac"`` and ``"sic"`` (ASTERIX System Area and System Identification Codes, 0-255, both or
neither, unique pairs) so ASTERIX records find their sensor::

    [{"id": "LJLJ", "kind": "radar", "sac": 25, "sic": 201,
      "lat_deg": 46.2237, "lon_deg": 14.4576, "height_m": 380.0,
      "range_error_m": 150.0, "azimuth_error_deg": 0.24,
      "range_sigma_m": 50.0, "azimuth_sigma_deg": 0.08,            # optional (default /3)
      "max_altitude_m": 0.0, "max_elevation_deg": 0.0,             # optional
      "estimate_bias": false,                                       # optional
      "range_offset_m": 0.0, "azimuth_offset_deg": 0.0,            # known offsets: optional
      "time_offset_s": 0.0},
     {"id": "ADSB", "kind": "position", "sac": 25, "sic": 1,
      "position_sigma_m": 30.0, "altitude_sigma_m": 15.0,          # altitude: optional
      "estimate_bias": false, "time_offset_s": 0.0}]                # its time offset: optional

A radar without ``lat_deg``/``lon_deg`` sits at the reference point. Unknown keys, wrong types,
NaN and bad values raise :class:`solver.InputError` at ``sensors[j].field``; JSON syntax errors
name the line and column.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..frames import LocalFrame
from ..inputs import InputError
from ..json_keys import TWICE, duplicate_key
from ..plots import validate_sensors
from ..sensors import PositionSensor, RadarSensor, Sensor, Site

Loc = tuple[str | int, ...]

_RADAR_KEYS = {"id", "kind", "sac", "sic", "lat_deg", "lon_deg", "height_m", "range_error_m",
               "azimuth_error_deg", "range_sigma_m", "azimuth_sigma_deg", "max_altitude_m",
               "max_elevation_deg", "altitude_sigma_m", "estimate_bias", "range_offset_m",
               "azimuth_offset_deg", "time_offset_s"}
_POSITION_KEYS = {"id", "kind", "sac", "sic", "position_sigma_m", "altitude_sigma_m",
                  "estimate_bias", "time_offset_s"}
MAX_OFFSETS = {"range_offset_m": 5_000.0, "azimuth_offset_deg": 10.0, "time_offset_s": 60.0}
"""Known offsets beyond these are refused (no registration finds more)."""


@dataclass(frozen=True)
class KnownOffsets:
    """A sensor's known offsets (a registration's result: ``sensors.json``'s ``range_bias_m``,
    ``azimuth_bias_deg``, ``time_bias_s`` of an earlier run with ``estimate_bias``), taken off
    its plots before anything else: range minus ``range_m``, azimuth minus ``azimuth_deg``,
    time minus ``time_s`` (a report late by ``time_s`` is of that much earlier). They reach
    every track the sensor sees, those it sees alone too, whose offsets cannot be estimated."""

    range_m: float = 0.0
    azimuth_deg: float = 0.0
    time_s: float = 0.0

    def __bool__(self) -> bool:
        return bool(self.range_m or self.azimuth_deg or self.time_s)


@dataclass(frozen=True)
class SensorSet:
    """The sensors of a recording, their ASTERIX codes and the recording's plane.

    ``codes`` maps ``(sac, sic)`` to an index into ``sensors``; ``reference`` is the
    sensor file's reference, else None (:func:`solver.io.split.recording_frame` then picks
    one)."""

    sensors: tuple[Sensor, ...]
    codes: dict[tuple[int, int], int]
    reference: LocalFrame | None = None
    offsets: tuple[KnownOffsets, ...] = ()
    """Per sensor (in order) its known offsets; empty: none."""

    def known_offsets(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(range_m, azimuth_deg, time_s)`` per sensor index, or None when no sensor has
        any (:class:`KnownOffsets`)."""
        return offset_arrays(self.offsets)

    def index(self) -> dict[str, int]:
        """Sensor id -> index."""
        return {s.id: j for j, s in enumerate(self.sensors)}

    def by_code(self, sac: int, sic: int) -> Sensor | None:
        j = self.codes.get((sac, sic))
        return None if j is None else self.sensors[j]


def load_sensors(path: str | Path) -> SensorSet:
    """Read and validate a sensor file (see the module docstring)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as e:  # Latin-1, UTF-16 (a fuzz helper: a traceback)
        raise InputError(("sensors",), f"{path} is not UTF-8 text (byte {e.start})") from None
    try:
        return parse_sensors(text)
    except InputError as e:  # named by the file, as the command line knows it
        raise InputError(e.loc, f"{e.message} (in {path})") from None


def parse_sensors(text: str | object) -> SensorSet:
    """A :class:`SensorSet` from the file's JSON text or its already-parsed value."""
    if isinstance(text, str):
        def no_constant(name: str) -> object:
            raise ValueError(f"{name} is not a number JSON allows")
        try:
            value = json.loads(text, parse_constant=no_constant)
        except json.JSONDecodeError as e:
            raise InputError(("sensors",), f"is not valid JSON: {e.msg} at line {e.lineno} "
                             f"column {e.colno}") from None
        except ValueError as e:
            raise InputError(("sensors",), f"is not valid JSON: {e}") from None
        except RecursionError:  # json's C scanner recurses per nesting level
            raise InputError(("sensors",), "is nested too deeply (a sensor file is a list of "
                             "sensor objects)") from None
        twice = duplicate_key(text)
        if twice is not None:
            raise InputError(("sensors", *twice) if isinstance(value, list) else twice, TWICE)
    else:
        value = text
    reference = None
    if isinstance(value, dict):
        extra = set(value) - {"sensors", "reference"}
        if extra:
            raise InputError((sorted(extra)[0],), "is not a key of the sensor file (keys: "
                             "sensors, reference)")
        if "reference" in value:
            ref = value["reference"]
            if not isinstance(ref, dict) or set(ref) != {"lat_deg", "lon_deg"}:
                raise InputError(("reference",), "must be {\"lat_deg\": ..., \"lon_deg\": ...}")
            reference = LocalFrame(_number(ref, "lat_deg", ("reference",)),  # type: ignore[arg-type]
                                   _number(ref, "lon_deg", ("reference",)))  # type: ignore[arg-type]
            reference.validate()
        value = value.get("sensors")
    if not isinstance(value, list) or not value:
        raise InputError(("sensors",), "must be a non-empty list of sensor objects")
    sensors: list[Sensor] = []
    codes: dict[tuple[int, int], int] = {}
    offsets: list[KnownOffsets] = []
    for j, obj in enumerate(value):
        loc: Loc = ("sensors", j)
        sensor, code = _sensor(obj, loc)
        offsets.append(_offsets(obj, loc))
        if code is not None:
            if code in codes:
                raise InputError((*loc, "sic"), f"SAC {code[0]} / SIC {code[1]} repeats "
                                 f"sensors[{codes[code]}]")
            codes[code] = j
        sensors.append(sensor)
    try:
        validate_sensors(tuple(sensors))
    except InputError as e:  # the file's fields are in degrees
        last = e.loc[-1]
        if isinstance(last, str) and last.endswith("_rad"):
            raise InputError((*e.loc[:-1], last[:-4] + "_deg"), e.message) from None
        raise
    if reference is None:  # the plane's default tangent point: the first radar's site
        j, first = next(((j, s) for j, s in enumerate(sensors)
                         if isinstance(s, RadarSensor) and s.site is not None), (None, None))
        if first is not None and first.site is not None:
            try:
                LocalFrame(first.site.lat_deg, first.site.lon_deg).validate(("sensors", j))
            except InputError as e:  # refused here, not when a job or run starts with it
                raise InputError(e.loc, f"{e.message}: the plane's reference defaults to the "
                                 "first radar's site; give the file a `reference` away from "
                                 "the pole") from None
    return SensorSet(tuple(sensors), codes, reference, tuple(offsets))


def offset_arrays(offsets: Sequence[KnownOffsets]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(range_m, azimuth_deg, time_s)`` of each sensor's known offsets (in order), or None
    when none has any."""
    if not any(offsets):
        return None
    return (np.array([o.range_m for o in offsets]), np.array([o.azimuth_deg for o in offsets]),
            np.array([o.time_s for o in offsets]))


def take_off_offsets(known: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
                     sensor: np.ndarray, t: np.ndarray, range_m: np.ndarray,
                     azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plots' ``(t, range_m, azimuth_deg)`` with their sensors' (index ``sensor``) known
    offsets (:func:`offset_arrays`) taken off: the one rule of the sensor file, a request and
    a job (a report late by ``time_s`` is of that much earlier)."""
    if known is None:
        return t, range_m, azimuth_deg
    return t - known[2][sensor], range_m - known[0][sensor], azimuth_deg - known[1][sensor]


def _offsets(obj: dict, loc: Loc) -> KnownOffsets:
    values = {}
    for name, top in MAX_OFFSETS.items():
        v = _number(obj, name, loc, default=0.0)
        if abs(v) > top:  # type: ignore[arg-type]
            raise InputError((*loc, name), f"must be within +-{top:g} ({v:g})")
        values[name] = v
    return KnownOffsets(values["range_offset_m"], values["azimuth_offset_deg"],  # type: ignore[arg-type]
                        values["time_offset_s"])  # type: ignore[arg-type]


def _sensor(obj: object, loc: Loc) -> tuple[Sensor, tuple[int, int] | None]:
    if not isinstance(obj, dict):
        raise InputError(loc, "must be an object")
    kind = obj.get("kind")
    if kind not in ("radar", "position"):
        raise InputError((*loc, "kind"), f"must be \"radar\" or \"position\" ({kind!r})")
    allowed = _RADAR_KEYS if kind == "radar" else _POSITION_KEYS
    extra = sorted(set(obj) - allowed)
    if extra:
        raise InputError((*loc, extra[0]), f"is not a field of a {kind} sensor (fields: "
                         f"{', '.join(sorted(allowed))})")
    sid = obj.get("id")
    if not isinstance(sid, str) or not sid:
        raise InputError((*loc, "id"), "must be a non-empty string")
    code = None
    if ("sac" in obj) != ("sic" in obj):
        missing = "sic" if "sac" in obj else "sac"
        raise InputError((*loc, missing), "is required with the other ASTERIX code")
    if "sac" in obj:
        code = (_code(obj, "sac", loc), _code(obj, "sic", loc))
    bias = obj.get("estimate_bias", False)
    if not isinstance(bias, bool):
        raise InputError((*loc, "estimate_bias"), "must be true or false")
    if kind == "position":
        sensor: Sensor = PositionSensor(
            sid, _number(obj, "position_sigma_m", loc, required=True),  # type: ignore[arg-type]
            _number(obj, "altitude_sigma_m", loc, default=15.0),  # type: ignore[arg-type]
            estimate_bias=bias)
        return sensor, code
    if ("lat_deg" in obj) != ("lon_deg" in obj):
        missing = "lon_deg" if "lat_deg" in obj else "lat_deg"
        raise InputError((*loc, missing), "is required with the other site coordinate (or "
                         "omit both to put the radar at the reference point)")
    site = None
    if "lat_deg" in obj:
        site = Site(_number(obj, "lat_deg", loc), _number(obj, "lon_deg", loc),  # type: ignore[arg-type]
                    _number(obj, "height_m", loc, default=0.0))  # type: ignore[arg-type]
    elif "height_m" in obj:
        raise InputError((*loc, "height_m"), "needs lat_deg and lon_deg")
    deg = math.pi / 180
    sigma_psi = _number(obj, "azimuth_sigma_deg", loc)
    sensor = RadarSensor(
        _number(obj, "range_error_m", loc, required=True),  # type: ignore[arg-type]
        _number(obj, "azimuth_error_deg", loc, required=True) * deg,  # type: ignore[operator]
        range_sigma_m=_number(obj, "range_sigma_m", loc),
        azimuth_sigma_rad=None if sigma_psi is None else sigma_psi * deg,
        max_altitude_m=_number(obj, "max_altitude_m", loc, default=0.0),  # type: ignore[arg-type]
        max_elevation_rad=_number(obj, "max_elevation_deg", loc, default=0.0) * deg,  # type: ignore[operator]
        altitude_sigma_m=_number(obj, "altitude_sigma_m", loc, default=0.0),  # type: ignore[arg-type]
        id=sid, site=site, estimate_bias=bias)
    return sensor, code


def _number(obj: dict, name: str, loc: Loc, *, required: bool = False,
            default: float | None = None) -> float | None:
    if name not in obj or obj[name] is None:
        if required:
            raise InputError((*loc, name), "is required")
        return default
    v = obj[name]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise InputError((*loc, name), f"must be a finite number ({v!r})")
    return float(v)


def _code(obj: dict, name: str, loc: Loc) -> int:
    v = obj[name]
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
        raise InputError((*loc, name), f"must be an integer in [0, 255] ({v!r})")
    return v
