"""Are the manoeuvres read off the segments the ones the aircraft flew? (``solver.manoeuvres``)

    python -m benchmarks.manoeuvres                  # dev seeds 100 and 101 (~2 min)
    python -m benchmarks.manoeuvres --seeds 0 1 2 3 --out manoeuvres_heldout.md  # held out

For every track (the six ADS-B flights and the synthetic seed-like one) and radar profile, the
truth's manoeuvres are found by the same rule (:func:`solver.manoeuvres.find_manoeuvres`) on
1-s pieces of the true trajectory (``u = v phi'``, ``w = v'``, from the truth's splines,
averaged over 21 s: see :func:`truth_manoeuvres`), and
compared with those of the refined reconstruction's segments and, as the obvious alternative, of
the IMM smoother's states at the plots (each interval between plots one piece with the turn and
speed change between its ends).

A found manoeuvre *matches* a true one of the same kind and direction when their time spans
overlap. Reported: recall (true ones matched), precision (found ones that match a true one),
the median and 90th percentile of the onset error ``|t_start - t_start_true|`` and of the
change error (heading, deg, for turns; speed, m/s, for speed changes) of the matched pairs.
Writes ``benchmarks/results/manoeuvres.md``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from tqdm import tqdm

from solver.manoeuvres import Manoeuvre, find_manoeuvres, from_segments
from solver.reconstruct import reconstruct
from solver.results import StateSeries

from . import baselines
from .profiles import PROFILES
from .run import publish
from .simulate import simulate
from .truth import Truth, load_truth, truth_names

PROFILE_NAMES = ("seed000", "seed001", "ssr")
SMOOTH_S = 21.0


def truth_manoeuvres(truth: Truth, smooth_s: float = SMOOTH_S) -> list[Manoeuvre]:
    """The truth's manoeuvres from 1-s pieces: each piece's ``u = v phi'`` and ``w = v'`` at
    its middle, averaged over ``smooth_s`` (the flights' ADS-B velocities, every 5 s, make
    ``|v'|`` 0.25-0.34 m/s^2 in the median unsmoothed: noise the radars cannot see)."""
    t = np.arange(truth.t[0], truth.t[-1], 1.0)
    mid = t[:-1] + 0.5
    s0, sm = truth.at(t[:-1]), truth.at(mid)
    k = np.ones(int(smooth_s)) / int(smooth_s)
    u = np.convolve(sm.speed * truth.turn_rate_at(mid), k, mode="same")
    w = np.convolve(np.diff(truth.at(t).speed), k, mode="same")
    return find_manoeuvres(t[:-1], t[1:], s0.x, s0.z, s0.heading, s0.speed, u, w)


def state_manoeuvres(s: StateSeries) -> list[Manoeuvre]:
    """Manoeuvres of states at plot times: each interval one piece whose constant ``(u, w)``
    take it from the heading and speed at its start to those at its end."""
    dt = np.diff(s.t)
    ok = dt > 0
    phi, v = np.unwrap(s.heading), s.speed
    dphi, dv = np.diff(phi)[ok], np.diff(v)[ok]
    t0, t1, dt = s.t[:-1][ok], s.t[1:][ok], dt[ok]
    w = dv / dt
    # phi' = u / v with v = v0 + w t: dphi = (u / w) ln(v1 / v0), or u dt / v0 when w = 0
    ratio = np.log(v[1:][ok] / v[:-1][ok])
    u = np.where(np.abs(ratio) > 1e-12, dphi * w / np.where(ratio == 0, 1, ratio),
                 dphi * v[:-1][ok] / dt)
    return find_manoeuvres(t0, t1, s.x[:-1][ok], s.z[:-1][ok], s.heading[:-1][ok],
                           v[:-1][ok], u, w)


def compare(found: list[Manoeuvre], true: list[Manoeuvre]) -> dict[str, list[float] | int]:
    """Matches (same kind and direction, overlapping spans): counts and the errors."""
    out: dict[str, list[float] | int] = {"true": len(true), "found": len(found), "matched": 0,
                                         "right": 0, "onset": [], "change": []}
    for m in true:
        hits = [f for f in found if f.kind == m.kind and f.direction == m.direction
                and f.t_start < m.t_end and m.t_start < f.t_end]
        if hits:
            out["matched"] += 1  # type: ignore[operator]
            f = min(hits, key=lambda f: abs(f.t_start - m.t_start))
            out["onset"].append(abs(f.t_start - m.t_start))  # type: ignore[union-attr]
            err = (f.heading_change_deg - m.heading_change_deg if m.kind == "turn"
                   else f.speed_change - m.speed_change)
            out["change"].append(abs(err))  # type: ignore[union-attr]
    out["right"] = sum(any(f.kind == m.kind and f.direction == m.direction and
                           f.t_start < m.t_end and m.t_start < f.t_end for m in true)
                       for f in found)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[100, 101])
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", default="manoeuvres.md", help="results file ('' : print only)")
    args = ap.parse_args()
    started = time.perf_counter()
    pools: dict[tuple[str, str, str], list[dict]] = {}
    jobs = [(p, n, s) for p in PROFILE_NAMES for n in truth_names() for s in args.seeds]
    for profile, name, seed in tqdm(jobs, disable=args.no_progress):
        truth = load_truth(name)
        true = truth_manoeuvres(truth)
        sim = simulate(truth, PROFILES[profile], seed)
        radar = PROFILES[profile].radar()
        rec = reconstruct(sim.plots, radar)
        imm = baselines.imm_smoother(sim.plots, radar,
                                     baselines.TUNED.get(profile, baselines.Tuning()).imm_smoother)
        for est, found in (("recon-refined", from_segments(rec.segments)),
                           ("imm-smoother", state_manoeuvres(imm))):
            for kind in ("turn", "speed_change"):
                pools.setdefault((profile, est, kind), []).append(compare(
                    [f for f in found if f.kind == kind], [m for m in true if m.kind == kind]))
    md = ["# Manoeuvres read off the reconstruction against the truth's", "",
          f"`python -m benchmarks.manoeuvres --seeds {' '.join(map(str, args.seeds))}"
          + (f" --out {args.out}" if args.out != "manoeuvres.md" else "") + "` "
          f"({time.perf_counter() - started:.0f} s): {len(truth_names())} tracks, seeds "
          f"{args.seeds}, the default thresholds of `solver/manoeuvres.py`; see the module "
          "docstring of `benchmarks/manoeuvres.py` for the rule and the matching.", "",
          "| profile | kind | estimator | true | found | recall | precision | onset error "
          "median / p90 (s) | change error median / p90 |",
          "|---|---|---|---:|---:|---:|---:|---|---|"]
    for (profile, est, kind), rows in pools.items():
        true = sum(r["true"] for r in rows)
        found = sum(r["found"] for r in rows)
        onset = np.concatenate([r["onset"] for r in rows] + [[]])
        change = np.concatenate([r["change"] for r in rows] + [[]])
        unit = "deg" if kind == "turn" else "m/s"
        md.append(f"| {profile} | {kind} | {est} | {true} | {found} | "
                  f"{sum(r['matched'] for r in rows) / max(true, 1):.2f} | "
                  f"{sum(r['right'] for r in rows) / max(found, 1):.2f} | "
                  + (f"{np.median(onset):.0f} / {np.percentile(onset, 90):.0f} | "
                     f"{np.median(change):.1f} / {np.percentile(change, 90):.1f} {unit} |"
                     if onset.size else "- | - |"))
    if args.out:
        publish(args.out, md)
    else:
        print("\n".join(md))


if __name__ == "__main__":
    main()
