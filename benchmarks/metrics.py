"""Error metrics of an estimate against the truth at the plot times.

Per run: horizontal position errors ``e_i = |(x, z)_est - (x, z)_true|`` and ground-speed errors
``s_i = |v_est| - |v_true|``; summaries are RMS, 95th percentile, the same on the manoeuvre
plots (``|turn rate| > 1 deg/s`` in the truth), and the 95 % ellipse coverage: the share of
truth positions inside the estimate's 95 % position ellipse, ``d^T P^-1 d <= chi2_2(0.95)``
(= ``-2 ln 0.05`` = 5.991), where a covariance is given. Runs are pooled by concatenating their
per-plot errors, so a long track weighs more than a short one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from solver.inputs import FloatArray
from solver.results import StateSeries

CHI2_2DOF_95 = -2.0 * np.log(0.05)


@dataclass
class RunErrors:
    """Per-plot errors of one estimator on one simulated run.

    ``inside95`` is NaN where no covariance was given (or it was not positive definite)."""

    pos: FloatArray
    speed: FloatArray
    manoeuvre: FloatArray
    inside95: FloatArray
    wall_s: float
    n_plots: int
    cpu_s: float = float("nan")


def errors(est: StateSeries, truth: StateSeries, manoeuvre: FloatArray,
           wall_s: float = float("nan"), cpu_s: float = float("nan")) -> RunErrors:
    """Errors of ``est`` against ``truth`` (same times, same order)."""
    if len(est) != len(truth) or not np.allclose(est.t, truth.t, rtol=0, atol=1e-6):
        raise ValueError(f"estimate has {len(est)} states at other times than the "
                         f"{len(truth)} truth states")
    dx, dz = est.x - truth.x, est.z - truth.z
    return RunErrors(np.hypot(dx, dz), est.speed - truth.speed, np.asarray(manoeuvre, bool),
                     inside_ellipse95(est.cov, dx, dz), wall_s, len(truth), cpu_s)


def inside_ellipse95(cov: FloatArray | None, dx: FloatArray, dz: FloatArray) -> FloatArray:
    """1.0 where ``(dx, dz)`` lies in the 95 % ellipse of ``cov[:, :2, :2]``, 0.0 outside, NaN
    where the covariance is missing or not positive definite."""
    n = dx.shape[0]
    if cov is None:
        return np.full(n, np.nan)
    p = np.asarray(cov, dtype=float)[:, :2, :2]
    a, b, c = p[:, 0, 0], p[:, 0, 1], p[:, 1, 1]
    det = a * c - b * b
    ok = np.isfinite(det) & (det > 0) & (a > 0)
    safe = np.where(ok, det, 1.0)
    m2 = (c * dx * dx - 2 * b * dx * dz + a * dz * dz) / safe
    return np.where(ok, (m2 <= CHI2_2DOF_95).astype(float), np.nan)


def rms(values: FloatArray) -> float:
    """Root mean square of the finite values (NaN if there are none)."""
    v = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(v * v))) if v.size else float("nan")


def p95(values: FloatArray) -> float:
    """95th percentile (linear interpolation) of the finite values (NaN if none)."""
    v = values[np.isfinite(values)]
    return float(np.percentile(v, 95)) if v.size else float("nan")


def summarize(runs: Sequence[RunErrors]) -> dict[str, float]:
    """Pooled metrics of several runs (see the module docstring)."""
    pos = np.concatenate([r.pos for r in runs])
    speed = np.concatenate([r.speed for r in runs])
    man = np.concatenate([r.manoeuvre for r in runs])
    inside = np.concatenate([r.inside95 for r in runs])
    wall = np.array([r.wall_s for r in runs])
    cpu = np.array([r.cpu_s for r in runs])
    n = np.array([r.n_plots for r in runs])
    covered = inside[np.isfinite(inside)]
    return {
        "rms_pos": rms(pos),
        "rms_speed": rms(speed),
        "p95_pos": p95(pos),
        "rms_pos_man": rms(pos[man]),
        "rms_speed_man": rms(speed[man]),
        "p95_pos_man": p95(pos[man]),
        "coverage95": float(covered.mean()) if covered.size else float("nan"),
        "wall_s_per_track": float(np.mean(wall)),
        "plots_per_s": float(n.sum() / wall.sum()) if wall.sum() > 0 else float("nan"),
        "plots_per_cpu_s": float(n.sum() / cpu.sum()) if cpu.sum() > 0 else float("nan"),
        "n_runs": len(runs),
        "n_plots": int(n.sum()),
        "n_manoeuvre_plots": int(man.sum()),
    }
