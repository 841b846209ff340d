"""Every estimator the benchmark compares, behind one signature: plots + radar -> estimate.

Names: ``raw`` (the plot points); baselines ``ss-cv-kf``, ``ss-cv-rts`` (Stone Soup), ``fp-imm``
(FilterPy), ``imm-smoother`` (IMM fixed-interval smoother tuned per profile; neither library has
one) and ``imm-smoother-kim`` (the same with Kim's backward mode weights: faster, less accurate);
the product's filters ``filter-<name>`` (``solver.estimation.run_filter``); the product's
reconstruction ``recon-<method>-m<window>-<criterion>`` (``solver.reconstruct``), e.g.
``recon-refined-m3-R2``. A ``+alt`` suffix (``ss-cv-rts+alt``, ``imm-smoother+alt``,
``recon-refined-m3-R2+alt``) runs the estimator on plots that carry the true altitude (an SSR's
Mode C); those run on the ``ssr`` profile only.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable
from dataclasses import dataclass, field

from solver.config import ReconstructionConfig
from solver.inputs import Plots, Radar
from solver.results import Reconstruction, StateSeries

from . import baselines

FILTER_NAMES_FALLBACK = ("singer", "quasi_optimal", "fuzzy", "alpha_beta", "cv_rts", "imm",
                         "imm_smoother")
ALTITUDE_PROFILES = ("ssr",)


@dataclass
class Estimate:
    """States at the plot times, plus the reconstruction (segments, samples) when there is one."""

    states: StateSeries
    reconstruction: Reconstruction | None = None


@dataclass(frozen=True)
class Estimator:
    """One named estimator; ``kind`` is ``reference``, ``baseline``, ``filter`` or ``recon``."""

    name: str
    kind: str
    run: Callable[[Plots, Radar, str], Estimate] = field(compare=False)
    with_altitude: bool = False

    def applies_to(self, profile: str) -> bool:
        return not self.with_altitude or profile in ALTITUDE_PROFILES


def _baseline(fn: Callable[[Plots, Radar, str], StateSeries]):
    return lambda plots, radar, profile: Estimate(fn(plots, radar, profile))


def _ss_cv(smooth: bool):
    def run(plots: Plots, radar: Radar, profile: str) -> StateSeries:
        tuning = baselines.TUNED.get(profile, baselines.Tuning())
        q = tuning.q_rts if smooth else tuning.q_kf
        return baselines.stonesoup_cv(plots, radar, q=q, smooth=smooth)
    return run


def _fp_imm(plots: Plots, radar: Radar, profile: str) -> StateSeries:
    return baselines.filterpy_imm(plots, radar, baselines.TUNED.get(profile,
                                                                    baselines.Tuning()).imm)


def _imm_smoother(kim: bool):
    def run(plots: Plots, radar: Radar, profile: str) -> StateSeries:
        tuning = baselines.TUNED.get(profile, baselines.Tuning())
        return baselines.imm_smoother(plots, radar,
                                      tuning.imm_smoother_kim if kim else tuning.imm_smoother)
    return run


def _filter(name: str):
    def run(plots: Plots, radar: Radar, profile: str) -> Estimate:
        from solver.estimation import run_filter
        return Estimate(run_filter(name, plots, radar).states)
    return run


def recon_config(method: str, window: int, criterion: str, **kw) -> ReconstructionConfig:
    """The reconstruction settings behind ``recon-<method>-m<window>-<criterion>``."""
    return ReconstructionConfig(method=method, window_plots=window, criterion=criterion, **kw)


def recon_runner(config: ReconstructionConfig):
    def run(plots: Plots, radar: Radar, profile: str) -> Estimate:
        from solver.reconstruct import reconstruct
        rec = reconstruct(plots, radar, config)
        return Estimate(rec.at_plots, rec)
    return run


def filter_names() -> tuple[str, ...]:
    """The product's filters that run on one radar (``solver.estimation.SINGLE_SENSOR_NAMES``;
    the fusion variants need two sensors)."""
    try:
        from solver.estimation import SINGLE_SENSOR_NAMES
        return tuple(SINGLE_SENSOR_NAMES)
    except ImportError:
        return FILTER_NAMES_FALLBACK


def registry() -> dict[str, Estimator]:
    """All estimators by name."""
    est: list[Estimator] = [
        Estimator("raw", "reference", _baseline(lambda p, r, _: baselines.raw_plots(p, r))),
        Estimator("ss-cv-kf", "baseline", _baseline(_ss_cv(False))),
        Estimator("ss-cv-rts", "baseline", _baseline(_ss_cv(True))),
        Estimator("fp-imm", "baseline", _baseline(_fp_imm)),
        Estimator("imm-smoother", "baseline", _baseline(_imm_smoother(False))),
        Estimator("imm-smoother-kim", "baseline", _baseline(_imm_smoother(True))),
        Estimator("imm-smoother+alt", "baseline", _baseline(_imm_smoother(False)),
                  with_altitude=True),
        Estimator("ss-cv-rts+alt", "baseline", _baseline(_ss_cv(True)), with_altitude=True),
    ]
    est += [Estimator(f"filter-{n}", "filter", _filter(n)) for n in filter_names()]
    for method in ("refined", "sliding"):
        for window in (3, 4, 5):
            for crit in ("R2", "R1"):
                cfg = recon_config(method, window, crit)
                est.append(Estimator(f"recon-{method}-m{window}-{crit}", "recon",
                                     recon_runner(cfg)))
    est.append(Estimator("recon-refined-m3-R2+alt", "recon",
                         recon_runner(recon_config("refined", 3, "R2")), with_altitude=True))
    return {e.name: e for e in est}


DEFAULT_SET = (
    "raw", "ss-cv-kf", "ss-cv-rts", "fp-imm", "imm-smoother", "ss-cv-rts+alt",
    "imm-smoother+alt", "filter-*",
    "recon-refined-m3-R2", "recon-sliding-m3-R2", "recon-refined-m3-R2+alt",
)
"""The full run's estimators: every baseline and filter, the reconstruction's default and the
seed's method. The other windows and criteria (``recon-*``) cost a full reconstruction each; their
comparison is the tuning table (``python -m benchmarks.tune recon``)."""
QUICK_SET = ("raw", "ss-cv-kf", "ss-cv-rts", "fp-imm", "imm-smoother", "filter-*",
             "recon-refined-m3-R2",
             "recon-sliding-m3-R2")


def select(patterns: tuple[str, ...] | list[str]) -> list[Estimator]:
    """Estimators whose names match any of the glob ``patterns``, in registry order."""
    reg = registry()
    unknown = [p for p in patterns if not fnmatch.filter(reg, p)]
    if unknown:
        raise KeyError(f"no estimator matches {unknown}; known: {sorted(reg)}")
    return [e for n, e in reg.items() if any(fnmatch.fnmatchcase(n, p) for p in patterns)]
