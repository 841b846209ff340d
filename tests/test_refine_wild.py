"""Wild plots within reach of the track: the refinement's robust start (``smoother_guess``)."""

from dataclasses import replace
from functools import partial

import numpy as np
import pytest
from tracks import SEED_LIKE_LEGS, SEED_LIKE_START, make_track

import solver.refine as refine
from solver import Plots
from solver.config import ReconstructionConfig
from solver.inputs import Radar
from solver.reconstruct import reconstruct
from solver.refine.nodes import smoother_guess

SSR = Radar(150.0, np.radians(0.24), range_sigma_m=50.0, azimuth_sigma_rad=np.radians(0.08))


def wild_track(seed: int = 5, share: float = 0.01):
    """The seed-like track seen by an SSR every 5 s, ``share`` of the plots replaced by false
    plots within +-20 km and +-5 deg (as ``benchmarks/gating.py``); seed 5: 14 of them."""
    tr = make_track(SEED_LIKE_LEGS, SEED_LIKE_START, scan_s=5.0, sigma_r=50.0,
                    sigma_psi=np.radians(0.08), drop_in_turns=False, seed=seed)
    p = tr.plots
    rng = np.random.default_rng(seed)
    wild = rng.uniform(size=p.t.size) < share
    wild[:2] = False
    r, a = p.range_m.copy(), p.azimuth_rad.copy()
    r[wild] += rng.uniform(-20_000, 20_000, wild.sum())
    a[wild] += np.radians(rng.uniform(-5, 5, wild.sum()))
    return tr, Plots.from_arrays(p.t, r, a), wild


@pytest.mark.parametrize("robust", [True, False])
def test_wild_plots_within_reach_do_not_derail_the_refinement(robust, monkeypatch):
    """With the plain smoother's start (``huber=None``) a few false plots near a turn pulled
    the start kilometres off and the refinement stayed there: 506 m RMS, 4.7 km at worst;
    with the robust start 46 m (183 m at worst), as without false plots (the teeth: the plain
    start must fail here)."""
    tr, plots, wild = wild_track()
    if not robust:
        monkeypatch.setattr(refine, "smoother_guess", partial(smoother_guess, huber=None))
    rec = reconstruct(plots, SSR)
    e = np.hypot(rec.at_plots.x - tr.x, rec.at_plots.z - tr.z)[~wild]
    rms = float(np.sqrt(np.mean(e**2)))
    if robust:
        assert rms < 60.0 and e.max() < 400.0, (rms, e.max())
    else:
        assert rms > 200.0, rms


def test_the_sliding_windows_give_wild_plots_no_weight():
    """The seed's windows have no defence of their own: the plots a gated CV smoother leaves
    out get no weight (named in a warning), the states there come from the track; without that
    one false plot spoiled its windows (1 % false plots, two seed001 dev tracks: 552 -> 1,034
    and 628 -> 1,687 m RMS; now 557 and 629 m)."""
    tr = make_track(SEED_LIKE_LEGS[:4], SEED_LIKE_START, scan_s=10.0, sigma_r=100.0,
                    sigma_psi=np.radians(0.2), drop_in_turns=False, seed=3)
    p = tr.plots
    wild = [20, 61, 95]
    r, a = p.range_m.copy(), p.azimuth_rad.copy()
    r[wild] += [12_000.0, -9_000.0, 7_000.0]
    a[wild] += np.radians([2.0, -3.0, 1.0])
    radar = Radar(300.0, np.radians(0.6), range_sigma_m=100.0, azimuth_sigma_rad=np.radians(0.2))
    config = ReconstructionConfig(method="sliding")
    keep = np.setdiff1d(np.arange(len(tr.t)), wild)

    def rms(rec) -> float:
        return float(np.sqrt(np.mean(np.hypot(rec.at_plots.x - tr.x, rec.at_plots.z - tr.z)[keep]
                                     ** 2)))

    clean = reconstruct(p, radar, config)
    rec = reconstruct(Plots.from_arrays(p.t, r, a), radar, config)
    assert len(rec.at_plots.t) == len(tr.t)
    assert any(w.startswith("3 plot(s) far from a gated constant-velocity smoother")
               and w.endswith("[20, 61, 95]") for w in rec.diagnostics.warnings)
    assert rms(rec) < 1.1 * rms(clean), (rms(rec), rms(clean))
    off = replace(config, refine=replace(config.refine, outlier_gate=None))
    assert rms(reconstruct(Plots.from_arrays(p.t, r, a), radar, off)) > 1.5 * rms(rec)


def test_misfit_stretches_are_the_plots_near_far_ones_at_a_bound():
    """Plots within 60 s of a plot more than the gate from the track where u or v sits at a
    bound (the bounds bend the track off there) are no reference for the sensors; far plots
    with the controls free (a wild plot, a sensor's offset) and near ones at a bound are
    not."""
    from solver.inputs import Bounds
    from solver.refine.gate import MISFIT_MARGIN_S, misfit_stretches

    bounds = Bounds()
    t = np.arange(0.0, 1000.0, 10.0)
    sol = np.zeros((t.size, 6))
    sol[:, 3] = 200.0  # v free
    sol[40:45, 4] = bounds.u[1]  # u at its bound over nodes 40-44
    sol[80, 3] = bounds.v[0]  # v at its bound at node 80
    quad = np.ones(t.size)
    quad[[42, 60, 81]] = 100.0  # far (10 sigma): at u's bound, free, next to v's bound
    quad[43] = 1.0  # near, at the bound
    got = misfit_stretches(quad, t, sol, bounds, 5.0, np.arange(t.size))
    near = (np.abs(t - t[42]) <= MISFIT_MARGIN_S) | (np.abs(t - t[81]) <= MISFIT_MARGIN_S)
    np.testing.assert_array_equal(got, np.flatnonzero(near))
    assert misfit_stretches(quad, t, sol, bounds, None, np.arange(t.size)).size == 0


@pytest.mark.parametrize(("end", "offset_m"), [(0, -1900.0), (-1, 2000.0), (-1, -1900.0)])
def test_a_wild_plot_at_a_tracks_end_is_no_turn(end, offset_m):
    """A lone radar's first or last plot 2 km off: the lateral acceleration at its bound at
    the track's end took it for a turn harder than the bounds (kept, the next plot then 250-500
    m off and 13-14 good plots left out of the statistics; a tester's recording). At the ends
    no plot beyond can say it is a turn: it is given no weight, and the track fits the rest."""
    from test_refine_multisensor import SSR_A, _simulate

    table, *_ = _simulate((SSR_A,), ((4.8, 0.3),), noise=1.0, seed=5, t_end=400.0,
                          mode_c=True)
    order = np.argsort(table.t)
    r = table.range_m.copy()
    r[order[end]] += offset_m
    rec = reconstruct(replace(table, range_m=r))
    assert rec.residuals.gated[order[end]]
    assert abs(rec.residuals.range_m[order[1 if end == 0 else -2]]) < 4 * SSR_A.sigma_r
    assert rec.sensors[0].plots_wild == 1 and rec.sensors[0].plots_no_reference == 0
    # nor is the next plot, bent towards it in the first solve, said to be a turn (a tester)
    assert not [w for w in rec.diagnostics.warnings if "turn harder" in w]
