"""How much of each estimator's error is bias, and how much is noise? (issue 6, accuracy targets)

    python -m benchmarks.bias_variance                 # dev seeds 100 and 101 (~2 min)
    python -m benchmarks.bias_variance --seeds 100

Every dev track is simulated twice with the same seed, so with the same plot times: once as the
benchmark does and once with the radar's noise set to zero (the estimators still get the
radar's sigmas, so they weigh the plots exactly as in the noisy run). The noise-free run's error
is the estimator's bias: what its prior and model do to a perfectly measured track (and, without
altitude, the ``h^2 / 2r`` of taking slant range for ground range, the ``raw`` row). For a
bias ``b`` and total error ``e`` the table gives ``sqrt(e^2 - b^2)``, the part the noise adds
(exact when the noise adds an independent, zero-mean error). A prior that cuts corners shows as
a large bias and a small noise part; lowering its weights trades one for the other
(``python -m benchmarks.tune refine --grid``). Writes benchmarks/results/bias_variance.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from tqdm import tqdm

from .estimators import registry
from .metrics import rms
from .profiles import PROFILES
from .run import publish
from .simulate import simulate
from .truth import SYNTHETIC, load_truth, truth_names

ROWS = {  # profile (``+alt``: the true altitude with each plot) -> estimators
    "seed000": ("raw", "ss-cv-rts", "recon-refined-m3-R2"),
    "seed001": ("raw", "ss-cv-rts", "recon-refined-m3-R2"),
    "ssr": ("raw", "ss-cv-rts", "recon-refined-m3-R2"),
    "ssr+alt": ("ss-cv-rts+alt", "recon-refined-m3-R2+alt"),
}


def errors(profile: str, estimators: tuple[str, ...], names: list[str], seeds: list[int],
           progress: bool = True, t_max: float | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Per estimator: pooled position errors (m) of the noisy and the noise-free runs
    (``t_max``: the first that many seconds of each track)."""
    base, alt = profile.removesuffix("+alt"), profile.endswith("+alt")
    noisy = PROFILES[base]
    quiet = replace(noisy, sigma_r=0.0, sigma_psi=0.0)
    radar = noisy.radar()  # the same sigmas (weights) in both runs
    reg = registry()
    out: dict[str, dict[str, list]] = {e: {"noisy": [], "noise-free": []} for e in estimators}
    jobs = [(n, s) for n in names for s in seeds]
    for name, seed in tqdm(jobs, desc=profile, unit="run", disable=not progress):
        truth = load_truth(name)
        times = None
        for kind, prof in (("noisy", noisy), ("noise-free", quiet)):
            sim = simulate(truth, prof, seed, with_altitude=alt, t_max=t_max)
            if times is not None and not np.array_equal(times, sim.plots.t):
                raise RuntimeError(f"{name}: the noise-free run has other plot times")
            times = sim.plots.t
            for e in estimators:
                est = reg[e].run(sim.plots, radar, base).states
                out[e][kind].append(np.hypot(est.x - sim.truth.x, est.z - sim.truth.z))
    return {e: {k: np.concatenate(v) for k, v in d.items()} for e, d in out.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[100, 101],
                    help="noise seeds (default: the dev seeds 100 and 101)")
    ap.add_argument("--profiles", nargs="+", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    names = [n for n in truth_names() if n != SYNTHETIC]
    t0 = time.perf_counter()
    md_rows = []
    for profile in args.profiles:
        res = errors(profile, ROWS[profile], names, args.seeds, not args.no_progress)
        for e, d in res.items():
            total, bias = rms(d["noisy"]), rms(d["noise-free"])
            noise = np.sqrt(max(total**2 - bias**2, 0.0))
            md_rows.append(f"| {profile} | {e} | {total:.0f} | {bias:.0f} | {noise:.0f} |")
    md = [
        "# Bias and noise parts of the position error", "",
        f"`python -m benchmarks.bias_variance --seeds {' '.join(map(str, args.seeds))}` "
        f"({time.perf_counter() - t0:.0f} s): the six dev tracks, each simulated with the "
        "profile's noise and again with zero noise (same plot times, same weights). RMS "
        "horizontal position error (m) at the plots, pooled; noise part = "
        "`sqrt(total^2 - noise-free^2)`.", "",
        "| profile | estimator | RMS total | RMS noise-free (bias) | noise part |",
        "|---|---|---:|---:|---:|",
        *md_rows,
    ]
    publish("bias_variance.md", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
