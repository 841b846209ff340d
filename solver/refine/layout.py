"""Named layouts of the refinement NLP: which rows of the variable and parameter matrices hold
what (``layout["centre"]`` is a slice), for each problem variant.

A variant adds what the plots need beyond one radar's positions: ``altitude`` (the aircraft's
height and vertical rate per node, when radar plots without altitude meet other sensors) and
``biases`` (range, azimuth and time offsets of that many radars, estimated with the track).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..sensors import ALTITUDE_FIT_DEGREE


class Layout:
    """Consecutive named rows: ``Layout([("dt", 1), ("centre", 2)])["centre"] == slice(1, 3)``."""

    def __init__(self, fields: Sequence[tuple[str, int]]):
        self.slices: dict[str, slice] = {}
        offset = 0
        for name, size in fields:
            self.slices[name] = slice(offset, offset + size)
            offset += size
        self.size = offset

    def __getitem__(self, name: str) -> slice:
        return self.slices[name]

    def __contains__(self, name: str) -> bool:
        return name in self.slices

    def row(self, name: str) -> int:
        """The single row of a one-row field."""
        s = self.slices[name]
        assert s.stop - s.start == 1, name
        return s.start


class Variant(NamedTuple):
    """Problem variant: estimate the altitude; number of radars whose biases are estimated."""

    altitude: bool = False
    biases: int = 0


BIAS_TERMS = 3  # range offset (m), azimuth offset (rad), time offset (s) per radar
HD_MAX = 60.0  # m/s: vertical-rate bound (12 000 ft/min, beyond any airliner's)


def node_variables(v: Variant) -> Layout:
    """Per node: state ``x, z, phi, v``, controls ``u, w``, the L1 split of their changes
    ``du+, du-, dw+, dw-``; with altitude, the height ``h`` (m above the ellipsoid, or above the
    radar on a flat plane) and the vertical rate ``hd`` (constant until the next node)."""
    fields = [("x", 1), ("z", 1), ("phi", 1), ("v", 1), ("u", 1), ("w", 1),
              ("du", 2), ("dw", 2)]
    if v.altitude:
        fields += [("h", 1), ("hd", 1)]
    return Layout(fields)


def solution_columns(v: Variant) -> tuple[str, ...]:
    """Columns of a node solution array: ``x, z, phi, v, u, w`` (and ``h, hd``)."""
    return ("x", "z", "phi", "v", "u", "w") + (("h", "hd") if v.altitude else ())


def global_variables(v: Variant) -> Layout:
    """Per problem: each estimated radar's ``(range, azimuth, time)`` offsets."""
    return Layout([("bias", BIAS_TERMS * v.biases)])


def node_parameters(v: Variant) -> Layout:
    """Per node: ``dt`` to the next node; the plot's centre ``(cx, cz)`` and R2 entries
    ``(a, b, c)`` of its one-sigma ellipse; its weight (1 at a plot, 0 elsewhere or when gated);
    the L1 weights of control changes into this node; the scale of the level penalties on
    ``|u|``, ``|w|`` over the interval from this node. With altitude: the centre's dependence on
    the height (coefficients of ``s, s^2, s^3`` per axis, the ray, slant range and site height of
    :class:`solver.sensors.PlaneFixes`, ``s = (h - h_mid) / h_half``), the plot's measured
    altitude with its information (0: none), and the information of the vertical-rate change
    into this node. With biases: the centre's derivatives with respect to slant range and
    azimuth, and which radar (one-hot) the plot is from."""
    fields = [("dt", 1), ("centre", 2), ("info", 3), ("weight", 1), ("switch", 2),
              ("level", 2)]
    if v.altitude:
        fields += [("centre_h", 2 * ALTITUDE_FIT_DEGREE), ("ray", 2), ("slant", 1),
                   ("site_h", 1), ("h_mid", 1), ("h_half", 1), ("alt", 1), ("alt_info", 1),
                   ("hd_info", 1)]
    if v.biases:
        fields += [("d_range", 2), ("d_azimuth", 2), ("sensor", v.biases)]
    return Layout(fields)


def block_parameters(v: Variant) -> Layout:
    """Per block: the controls before its first node (``u_prev``, ``w_prev``), the pseudo-Huber
    threshold, the level penalties and their smoothing; with altitude the vertical rate before
    the first node; with biases the prior information (1 / sigma^2) of each offset and the
    weights ``g`` of the pseudo-measurement ``g . b_t = 0`` of the time offsets
    (``time_gauge``: when no sensor keeps absolute time, a shift common to every time offset
    moves the whole track in time and cannot be observed; :func:`solver.refine.time_reference`)."""
    fields = [("u_prev", 1), ("w_prev", 1), ("huber", 1), ("level_u", 1), ("level_w", 1),
              ("level_eps", 1)]
    if v.altitude:
        fields += [("hd_prev", 1)]
    if v.biases:
        fields += [("bias_info", BIAS_TERMS * v.biases), ("time_gauge", v.biases)]
    return Layout(fields)


def node_scale(v: Variant) -> np.ndarray:
    """IPOPT works on node variables divided by this: positions in units of 30 m, speed in
    10 m/s (9 % and 7 % fewer iterations than unscaled on the 18 dev runs of seeds 100 and 101;
    10 m or 100 m: 2-11 %), heights in 30 m, vertical rates in 1 m/s."""
    base = [30.0, 30.0, 1.0, 10.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
    return np.array(base + ([30.0, 1.0] if v.altitude else []))


def global_scale(v: Variant) -> np.ndarray:
    """Offsets in units of 30 m, 1 mrad, 1 s."""
    return np.tile([30.0, 1e-3, 1.0], v.biases)
