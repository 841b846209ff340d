"""Manoeuvres read off segments (solver.manoeuvres) against closed forms and the rule's edges."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from benchmarks.truth import SEED_LIKE_CONTROLS
from solver.manoeuvres import ManoeuvreSettings, find_manoeuvres, from_segments
from solver.motion import propagate
from solver.results import Segment


def chain(controls, start=(0.0, 0.0, 0.0, 200.0), t0=0.0) -> list[Segment]:
    """Segments flying ``controls`` ``[(duration, u, w), ...]`` from ``start`` (x, z, phi, v)."""
    out, state = [], start
    for dur, u, w in controls:
        out.append(Segment(t0, t0 + dur, state[0], state[1], state[2] % (2 * math.pi),
                           state[3], u, w))
        state = tuple(float(a) for a in propagate(*state, u, w, dur))
        t0 += dur
    return out


def test_seed_like_controls_give_their_five_manoeuvres_exactly():
    segs = chain(SEED_LIKE_CONTROLS, start=(-120e3, 40e3, 0.0, 220.0))
    found = from_segments(segs)
    assert [(m.kind, m.direction) for m in found] == [
        ("speed_change", "decrease"), ("turn", "right"), ("speed_change", "increase"),
        ("turn", "left"), ("speed_change", "decrease")]
    starts = np.cumsum([0.0] + [d for d, _, _ in SEED_LIKE_CONTROLS])
    for m, k in zip(found, (1, 3, 5, 7, 9), strict=True):
        assert (m.t_start, m.t_end) == pytest.approx((starts[k], starts[k + 1]), abs=1e-9)
        assert m.peak_rate == pytest.approx(
            SEED_LIKE_CONTROLS[k][2] if m.kind == "speed_change" else
            math.degrees(SEED_LIKE_CONTROLS[k][1] / m.speed_start), rel=1e-12)
        # the end is where the next segment starts
        nxt = segs[k + 1]
        assert (m.x_end, m.z_end, m.speed_end) == pytest.approx((nxt.x, nxt.z, nxt.speed),
                                                                 abs=1e-6)
        assert m.heading_end_deg == pytest.approx(math.degrees(nxt.heading), abs=1e-9)
    # closed forms at constant speed: dphi = u T / v
    assert found[1].heading_change_deg == pytest.approx(math.degrees(5.0 * 115.2 / 150.0))
    assert found[3].heading_change_deg == pytest.approx(math.degrees(-6.0 * 104.7 / 200.0))
    assert [m.speed_change for m in found[::2]] == pytest.approx([-70.0, 50.0, -50.0])
    assert found[0].heading_change_deg == pytest.approx(0.0, abs=1e-12)


def test_turn_while_changing_speed_against_the_integrated_ode():
    """``phi' = u / v``, ``v' = w``: the heading change of a decelerating turn, integrated."""
    u, w, dur, v0 = 4.0, -0.8, 90.0, 180.0
    (m,) = [m for m in from_segments(chain([(dur, u, w)], start=(0, 0, 0.3, v0)))
            if m.kind == "turn"]
    ode = solve_ivp(lambda t, y: [u / y[1], w], (0, dur), [0.3, v0], rtol=1e-12, atol=1e-12)
    assert math.radians(m.heading_change_deg) == pytest.approx(ode.y[0, -1] - 0.3, rel=1e-9)
    assert m.speed_end == pytest.approx(ode.y[1, -1], rel=1e-12)


def test_the_rule_at_its_edges():
    v = 100.0
    u_at = lambda deg_s: v * math.radians(deg_s)  # noqa: E731 - u of a turn rate at v
    # under the least heading change (0.5 deg/s for 10 s: 5 deg): nothing
    assert from_segments(chain([(10.0, u_at(0.5), 0.0)], start=(0, 0, 0, v))) == []
    # slow all along (0.2 deg/s for 200 s: 40 deg, no segment at the threshold): nothing
    assert from_segments(chain([(200.0, u_at(0.2), 0.0)], start=(0, 0, 0, v))) == []
    # ramps at half the threshold or more belong to the turn; below it they do not
    segs = chain([(30.0, u_at(0.1), 0.0), (20.0, u_at(0.15), 0.0), (20.0, u_at(1.0), 0.0),
                  (20.0, u_at(0.13), 0.0), (30.0, 0.0, 0.0)], start=(0, 0, 0, v))
    (m,) = from_segments(segs)
    assert (m.t_start, m.t_end) == (30.0, 90.0)
    assert m.heading_change_deg == pytest.approx(20 * (0.15 + 1.0 + 0.13))
    # right then left at once: two turns; a zero-length segment inside a turn breaks nothing
    segs = chain([(20.0, u_at(1.0), 0.0), (0.0, 0.0, 0.0), (20.0, u_at(1.0), 0.0),
                  (40.0, -u_at(1.0), 0.0)], start=(0, 0, 0, v))
    found = from_segments(segs)
    assert [(m.direction, m.t_start, m.t_end) for m in found] == [("right", 0.0, 40.0),
                                                                   ("left", 40.0, 80.0)]
    assert [m.heading_change_deg for m in found] == pytest.approx([40.0, -40.0])
    assert from_segments([]) == []


def test_a_turn_across_north_and_a_full_orbit():
    v = 120.0
    segs = chain([(10.0, v * math.radians(3.0), 0.0)], start=(0, 0, math.radians(350.0), v))
    (m,) = from_segments(segs)
    assert m.heading_start_deg == pytest.approx(350.0)
    assert m.heading_end_deg == pytest.approx(20.0)
    assert m.heading_change_deg == pytest.approx(30.0)
    # an orbit and a half, cut into 19-s segments: one turn of 540 deg
    segs = chain([(19.0, -v * math.radians(3.0), 0.0)] * 9 + [(9.0, -v * math.radians(3.0),
                                                               0.0)], start=(0, 0, 0, v))
    (m,) = from_segments(segs)
    assert m.direction == "left" and m.heading_change_deg == pytest.approx(-540.0)
    assert m.heading_end_deg == pytest.approx(180.0)
    assert (m.x_end, m.z_end) == pytest.approx((0.0, -2 * v / math.radians(3.0)), abs=1e-6)


def test_settings_and_arrays_as_parquet_holds_them():
    segs = chain([(60.0, 0.0, 0.15), (60.0, 0.0, 0.0)], start=(0, 0, 0, 100.0))
    assert from_segments(segs) == []  # 0.15 m/s^2 is under the default 0.2
    loose = ManoeuvreSettings(acceleration=0.1, min_speed_change=5.0)
    (m,) = from_segments(segs, loose)
    assert (m.kind, m.direction, m.speed_change) == ("speed_change", "increase",
                                                     pytest.approx(9.0))
    cols = np.array([[s.t_start, s.t_end, s.x, s.z, s.heading, s.speed, s.u, s.w]
                     for s in segs])
    assert find_manoeuvres(*cols.T, settings=loose) == [m]


def test_the_benchmarks_truth_and_state_readings_agree_on_the_seed_like_track():
    """benchmarks.manoeuvres' two other readings on exact data: the truth's 1-s pieces
    (averaged over 21 s) and states every 10 s (as an estimator's at its plots) give the five
    manoeuvres of the controls, with their changes."""
    from benchmarks.manoeuvres import state_manoeuvres, truth_manoeuvres
    from benchmarks.truth import SYNTHETIC, load_truth

    truth = load_truth(SYNTHETIC)
    exact = from_segments(chain(SEED_LIKE_CONTROLS, start=(-120e3, 40e3, 0.0, 220.0)))
    t = np.arange(truth.t[0], truth.t[-1], 10.0)
    for found, slack in ((truth_manoeuvres(truth), 21.0), (state_manoeuvres(truth.at(t)), 10.0)):
        assert [(m.kind, m.direction) for m in found] == [(m.kind, m.direction) for m in exact]
        for m, e in zip(found, exact, strict=True):
            assert abs(m.t_start - e.t_start) <= slack and abs(m.t_end - e.t_end) <= slack
            assert m.heading_change_deg == pytest.approx(e.heading_change_deg, abs=1.0)
            assert m.speed_change == pytest.approx(e.speed_change, abs=1.0)
