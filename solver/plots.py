"""The validated plots table of one aircraft: one row per plot, a sensor column.

Times are strictly increasing within one sensor, not across sensors (two sensors may report
at the same instant). Radar rows carry a slant range and an azimuth, position rows a latitude
and a longitude; any row may carry an altitude (NaN: unknown). ``frame`` is the local plane of
the answer: None only for the seed's case of radars at the origin of a flat plane (the single
``radar`` request of api.md), where no geodesy is done.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from .frames import LocalFrame, check_lat_lon
from .inputs import (
    MAX_LON_DEG,
    MAX_RANGE_M,
    FloatArray,
    InputError,
    Plots,
    Radar,
    wrap_azimuth,
    wrap_lon,
)
from .sensors import (
    ALTITUDE_RANGE_M,
    ALTITUDE_SIGMA_RADAR_M,
    KNOWN_ALTITUDE_MARGIN_M,
    PlaneFixes,
    PositionSensor,
    RadarSensor,
    Sensor,
)

IntArray = np.ndarray


def _column(values: object, n: int) -> FloatArray:
    if values is None:
        return np.full(n, np.nan)
    return np.asarray(values, dtype=float).copy()


MAX_PLANE_SCALE = 1.5
"""Largest scale of the stereographic plane at a sensor's site or a position plot when the
reference is given (about 7800 km from it; a tester's reference 7207 km away, scale 1.40, still
gave the track within 10 m; 9991 km, scale 2.0, 2.6 km)."""


@dataclass(frozen=True)
class PlotTable:
    """Plots of one aircraft from one or several sensors (rows in input order).

    ``sensor[i]`` indexes ``sensors``; ``range_m``/``azimuth_rad`` are NaN on position rows,
    ``lat_deg``/``lon_deg`` NaN on radar rows, ``altitude_m`` NaN where unknown. Azimuths are
    normalised to [0, 2 pi).
    """

    sensors: tuple[Sensor, ...]
    t: FloatArray
    sensor: IntArray
    range_m: FloatArray
    azimuth_rad: FloatArray
    lat_deg: FloatArray
    lon_deg: FloatArray
    altitude_m: FloatArray
    frame: LocalFrame | None

    # ------------------------------------------------------------------------ building

    @classmethod
    def build(cls, sensors: Sequence[Sensor], t: object, sensor: Sequence[str] | IntArray,
              range_m: object = None, azimuth_rad: object = None, lat_deg: object = None,
              lon_deg: object = None, altitude_m: object = None,
              reference: LocalFrame | None = None) -> PlotTable:
        """Validated table from columns; ``sensor`` holds sensor ids (or indexes).

        The frame: ``reference`` if given, else the first radar site, else the first position
        plot; None (flat, no geodesy) when no sensor has a site, there is no position sensor
        and no reference.
        """
        sensors = tuple(sensors)
        validate_sensors(sensors)
        t_arr = np.asarray(t, dtype=float).copy()
        n = t_arr.shape[0] if t_arr.ndim == 1 else -1
        if n < 1:
            raise InputError(("plots",), "must contain at least one plot")
        idx = _sensor_index(sensors, sensor, n)
        lat, lon = _column(lat_deg, n), _column(lon_deg, n)
        lon = np.where(np.abs(lon) <= MAX_LON_DEG, wrap_lon(lon), lon)  # beyond: refused below
        frame = reference
        if frame is None:
            sited = [s for s in sensors if isinstance(s, RadarSensor) and s.site is not None]
            if sited:
                assert sited[0].site is not None
                frame = LocalFrame(sited[0].site.lat_deg, sited[0].site.lon_deg)
            elif any(isinstance(s, PositionSensor) for s in sensors):
                pos = np.flatnonzero([isinstance(sensors[k], PositionSensor) for k in idx])
                check_lat_lon(lat[pos], lon[pos], ("plots",))
                first = int(pos[0])
                frame = LocalFrame(float(lat[first]), float(lon[first]))
        table = cls(sensors, t_arr, idx, _column(range_m, n),
                    wrap_azimuth(_column(azimuth_rad, n)), lat, lon, _column(altitude_m, n),
                    frame)
        table.validate()
        if reference is not None:
            table._check_reference_reach()
        return table

    def _check_reference_reach(self) -> None:
        """A reference given so far from the sensors' sites or position plots that the plane's
        scale there exceeds :data:`MAX_PLANE_SCALE` is refused (``reference``): near its
        antipode the plane blows up (a tester's reference 19,981 km away: 59 km RMS)."""
        assert self.frame is not None
        sited = [s for s in self.sensors if isinstance(s, RadarSensor) and s.site is not None]
        lat = [s.site.lat_deg for s in sited]  # type: ignore[union-attr]
        lon = [s.site.lon_deg for s in sited]  # type: ignore[union-attr]
        pos = ~self.radar_rows()
        lat_all = np.concatenate([lat, self.lat_deg[pos]])
        lon_all = np.concatenate([lon, self.lon_deg[pos]])
        if not lat_all.size:
            return
        with np.errstate(all="ignore"):
            scale = np.asarray(self.frame.scale(*self.frame.to_plane(lat_all, lon_all)), float)
        worst = int(np.argmax(np.where(np.isfinite(scale), scale, np.inf)))
        if not scale[worst] <= MAX_PLANE_SCALE:
            km = float(self.frame.ground_distance(lat_all[worst], lon_all[worst])) / 1e3
            what = (f"the site of sensor {sited[worst].id!r}" if worst < len(sited)
                    else f"plots[{int(np.flatnonzero(pos)[worst - len(sited)])}]")
            raise InputError(("reference",), f"lies {km:.0f} km from the data ({what}), where "
                             f"the plane's scale would be "
                             f"{scale[worst]:.2f} (at most {MAX_PLANE_SCALE:g}: within about "
                             "7800 km): give a reference near the track")

    @classmethod
    def from_plots(cls, plots: Plots, radar: Radar) -> PlotTable:
        """The seed's single radar at the origin of a flat plane."""
        sensor = radar if isinstance(radar, RadarSensor) else RadarSensor(
            radar.range_error_m, radar.azimuth_error_rad, range_sigma_m=radar.range_sigma_m,
            azimuth_sigma_rad=radar.azimuth_sigma_rad, max_altitude_m=radar.max_altitude_m,
            max_elevation_rad=radar.max_elevation_rad, altitude_sigma_m=radar.altitude_sigma_m)
        n = len(plots)
        return cls.build((sensor,), plots.t, np.zeros(n, dtype=int), plots.range_m,
                         plots.azimuth_rad, altitude_m=plots.altitude_m)

    # ------------------------------------------------------------------------ checks

    def validate(self) -> None:
        """Raise :class:`InputError` naming the first bad plot and field."""
        if self.frame is not None:
            self.frame.validate()
        bad = np.flatnonzero(~np.isfinite(self.t))
        if bad.size:
            raise InputError(("plots", int(bad[0]), "t"), "must be a finite number")
        is_radar = self.radar_rows()
        for name in ("range_m", "azimuth_rad"):
            col = getattr(self, name)
            bad = np.flatnonzero(is_radar & ~np.isfinite(col))
            if bad.size:
                i = int(bad[0])
                raise InputError(("plots", i, name), "is required (a finite number) on a plot "
                                 f"of radar {self.sensors[self.sensor[i]].id!r}")
        for name in ("range_m", "azimuth_rad", "lat_deg", "lon_deg"):
            col = getattr(self, name)
            other = is_radar if name.startswith("l") else ~is_radar
            bad = np.flatnonzero(other & ~np.isnan(col))
            if bad.size:
                i = int(bad[0])
                s = self.sensors[self.sensor[i]]
                raise InputError(("plots", i, name), f"is not allowed on a plot of {s.kind} "
                                 f"sensor {s.id!r}")
        pos = np.flatnonzero(~is_radar)
        if pos.size:
            try:
                check_lat_lon(self.lat_deg[pos], self.lon_deg[pos], ("plots",))
            except InputError as e:  # re-index from the position rows to the table's rows
                raise InputError(("plots", int(pos[e.loc[1]]), e.loc[2]), e.message) from None
        rad = np.flatnonzero(is_radar)
        r = self.range_m
        bad = rad[r[rad] <= 0]
        if bad.size:
            raise InputError(("plots", int(bad[0]), "range_m"), "must be positive")
        bad = rad[r[rad] > MAX_RANGE_M]
        if bad.size:
            raise InputError(("plots", int(bad[0]), "range_m"),
                             f"must be below {MAX_RANGE_M:g} m (no radar sees further)")
        alt = self.altitude_m
        bad = np.flatnonzero(np.isinf(alt) | (alt < -1000) | (alt > 100_000))
        if bad.size:
            i = int(bad[0])
            raise InputError(("plots", i, "altitude_m"), f"must be finite and in [-1000, "
                             f"100000] m ({alt[i]})")
        if self.frame is None:  # flat plane: the altitude is above the radar, below the range
            bad = rad[(alt[rad] < 0) | (alt[rad] >= r[rad])]
            if bad.size:
                i = int(bad[0])
                raise InputError(("plots", i, "altitude_m"),
                                 f"must be finite, >= 0 and below the slant range ({alt[i]})")
        else:  # the straight line to a plot is at least its height difference with the site
            dh = alt[rad] - self.site_heights()[rad]
            for side, bad in (("above", rad[dh >= r[rad]]), ("below", rad[-dh >= r[rad]])):
                if bad.size:  # below: a plot was put on the site, a confident fix (audit)
                    i = int(bad[0])
                    raise InputError(("plots", i, "altitude_m"), f"({alt[i]}) is further "
                                     f"{side} the radar than the slant range reaches")
        for k in range(len(self.sensors)):
            rows = np.flatnonzero(self.sensor == k)
            step = np.flatnonzero(np.diff(self.t[rows]) <= 0)
            if step.size:
                i, j = int(rows[step[0] + 1]), int(rows[step[0]])
                raise InputError(("plots", i, "t"), f"is not after plots[{j}].t, the previous "
                                 f"plot of sensor {self.sensors[k].id!r} ({self.t[i]:g} <= "
                                 f"{self.t[j]:g})")

    def site_heights(self) -> FloatArray:
        """Each row's radar site height (m; 0 for other sensors) on a table with a frame."""
        assert self.frame is not None
        h = np.array([s.site_in(self.frame)[2] if isinstance(s, RadarSensor) else 0.0
                      for s in self.sensors])
        return h[self.sensor]

    # ------------------------------------------------------------------------ views

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def is_legacy(self) -> bool:
        """One radar at the origin of a flat plane: the seed's setting (api.md's ``radar``)."""
        return self.frame is None and len(self.sensors) == 1

    def time_order(self) -> IntArray:
        """Row indexes in time order (ties keep input order)."""
        return np.argsort(self.t, kind="stable")

    def radar_rows(self) -> np.ndarray:
        """``(n,)`` True where the plot is a radar's."""
        return np.array([isinstance(s, RadarSensor) for s in self.sensors])[self.sensor]

    def legacy(self) -> tuple[Plots, RadarSensor]:
        """The seed's ``(Plots, Radar)`` of a single-radar table (any frame)."""
        radar = self.sensors[0]
        if len(self.sensors) != 1 or not isinstance(radar, RadarSensor):
            raise InputError(("sensors",), "must hold exactly one radar for this method")
        alt = None if np.all(np.isnan(self.altitude_m)) else self.altitude_m
        return Plots(self.t, self.range_m, self.azimuth_rad, alt), radar

    def estimate_altitude(self) -> bool:
        """Whether the aircraft's height is estimated: when another sensor sees the aircraft
        too (a single radar cannot observe it) and some radar plots lack an altitude or carry
        one their radar calls uncertain (``altitude_sigma_m > 0``: a Mode C pressure altitude,
        then a measurement of the height; the plots stay at their own altitude)."""
        if len(self.sensors) < 2:
            return False
        soft = np.array([isinstance(s, RadarSensor) and s.altitude_sigma_m > 0
                         for s in self.sensors])[self.sensor]
        return bool(np.any(self.radar_rows() & (np.isnan(self.altitude_m) | soft)))

    def corrected(self, offsets: dict[int, tuple[float, float]]) -> PlotTable:
        """A copy whose radar plots of sensor ``k`` measured ``(r - b_r, psi - b_psi)`` for
        ``offsets[k] = (b_r, b_psi)`` (m, rad): where a radar with those offsets saw them."""
        r, psi = self.range_m.copy(), self.azimuth_rad.copy()
        for k, (b_r, b_psi) in offsets.items():
            rows = self.sensor == k
            r[rows] -= b_r
            psi[rows] = np.mod(psi[rows] - b_psi, 2 * np.pi)
        return replace(self, range_m=r, azimuth_rad=psi)

    def altitude_sigmas(self) -> FloatArray:
        """``(n,)`` sigma (m) of each plot's altitude as a measurement of the height: its
        sensor's ``altitude_sigma_m``, :data:`ALTITUDE_SIGMA_RADAR_M` for a radar's of 0."""
        return np.array([s.altitude_sigma_m if isinstance(s, PositionSensor)
                         or s.altitude_sigma_m > 0 else ALTITUDE_SIGMA_RADAR_M
                         for s in self.sensors], dtype=float)[self.sensor]

    def heights(self) -> tuple[float, float]:
        """The heights the aircraft may take: the general range (:data:`ALTITUDE_RANGE_M`)
        widened to the known altitudes (ADS-B at 17 km was held at 15 km, 2 km low) by
        :data:`KNOWN_ALTITUDE_MARGIN_M` plus 5 of their sigmas. The estimated height and every
        plot's reach (:meth:`RadarSensor.fixes`) take the same."""
        known = np.isfinite(self.altitude_m)
        margin = KNOWN_ALTITUDE_MARGIN_M + 5 * self.altitude_sigmas()[known]
        return (float(np.min(np.append(self.altitude_m[known] - margin, ALTITUDE_RANGE_M[0]))),
                float(np.max(np.append(self.altitude_m[known] + margin, ALTITUDE_RANGE_M[1]))))

    def fixes(self) -> PlaneFixes:
        """Every plot as a fix in the local plane (rows in table order)."""
        est = self.estimate_altitude()
        heights = self.heights()
        parts: list[tuple[np.ndarray, PlaneFixes]] = []
        for k, s in enumerate(self.sensors):
            rows = np.flatnonzero(self.sensor == k)
            if isinstance(s, RadarSensor):
                parts.append((rows, s.fixes(self.frame, self.range_m[rows],
                                            self.azimuth_rad[rows], self.altitude_m[rows], est,
                                            heights)))
            else:
                assert self.frame is not None
                parts.append((rows, s.fixes(self.frame, self.lat_deg[rows], self.lon_deg[rows])))
        return _merge(parts, len(self))


def _merge(parts: list[tuple[np.ndarray, PlaneFixes]], n: int) -> PlaneFixes:
    """Scatter per-sensor fixes back into table order."""
    from .geometry import Ellipses

    def gather(get: object) -> np.ndarray:
        first = get(parts[0][1])  # type: ignore[operator]
        out = np.zeros((n, *first.shape[1:]), dtype=first.dtype)
        for rows, f in parts:
            out[rows] = get(f)  # type: ignore[operator]
        return out

    ell = Ellipses(*(gather(lambda f, a=a: getattr(f.ellipses, a))
                     for a in ("cx", "cz", "psi", "A", "B")))
    names = ("altitude_free", "ray", "slant", "site_h", "poly", "h_mid", "h_half", "d_range",
             "d_azimuth")
    return PlaneFixes(ell, *(gather(lambda f, a=a: getattr(f, a)) for a in names))


def validate_sensors(sensors: tuple[Sensor, ...]) -> None:
    """Raise :class:`InputError` at ``sensors[j]`` for no sensor, an empty or repeated id, or a
    sensor's own bad value (site, accuracies)."""
    if not sensors:
        raise InputError(("sensors",), "must name at least one sensor")
    seen: dict[str, int] = {}
    for j, s in enumerate(sensors):
        if not isinstance(s.id, str) or not s.id:
            raise InputError(("sensors", j, "id"), "must be a non-empty string")
        if s.id in seen:
            raise InputError(("sensors", j, "id"), f"{s.id!r} repeats sensors[{seen[s.id]}].id")
        seen[s.id] = j
        s.validate_at(("sensors", j))


def _sensor_index(sensors: tuple[Sensor, ...], sensor: Sequence[str] | IntArray, n: int
                  ) -> IntArray:
    col = np.asarray(sensor)
    if col.shape != (n,):
        raise InputError(("plots",), f"the sensor column has {col.shape} values, expected {n}")
    if col.dtype.kind in "iu":
        bad = np.flatnonzero((col < 0) | (col >= len(sensors)))
        if bad.size:
            raise InputError(("plots", int(bad[0]), "sensor"), "indexes no sensor")
        idx = col.astype(int)
    else:
        ids = {s.id: j for j, s in enumerate(sensors)}
        idx = np.empty(n, dtype=int)
        for i, name in enumerate(col.tolist()):
            if name not in ids:
                raise InputError(("plots", i, "sensor"), f"{name!r} is not among the sensors' "
                                 f"ids ({', '.join(map(repr, ids))})")
            idx[i] = ids[name]
    used = np.bincount(idx, minlength=len(sensors))
    unused = np.flatnonzero(used == 0)
    if unused.size:
        j = int(unused[0])
        raise InputError(("sensors", j, "id"), f"{sensors[j].id!r} has no plots (every sensor "
                         "must be used)")
    return idx
