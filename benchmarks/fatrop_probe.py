"""Does a structure-exploiting interior-point solve pay for the refinement? (issue 17)

IPOPT factorizes the refinement's KKT system with MUMPS, a general sparse solver. FATROP
(shipped with CasADi as an ``nlpsol`` plugin) is an interior-point method for optimal-control
problems that solves the same Newton step by a Riccati recursion over the stages. This probe
states the one-radar block NLP of :mod:`solver.refine.nlp` in FATROP's stage form and runs it
in place of IPOPT on the dev tracks, so the two solve the same blocks from the same starts.

Stage form: stage ``k`` (node ``k``) has the state ``(x, z, phi, v, u_prev, w_prev)`` (the
previous node's controls, so the L1 change ``u_k - u_prev,k = du+ - du-`` is a stage
constraint) and the controls ``(u, w, du+, du-, dw+, dw-)``; the gap-closing constraint is
``state_{k+1} - (F(s_k, u_k, w_k, dt_k), u_k, w_k) = 0`` and the cost is the same sum over
nodes. Stage 0's ``u_prev, w_prev`` are held at the block's values by equal bounds. The
polish solve (changes held at zero by bounds) runs cold: FATROP takes no multipliers here.

    python -m benchmarks.fatrop_probe [--profile seed000] [--tracks 7] [--out FILE]
"""

from __future__ import annotations

import argparse
import time
from functools import cache
from typing import ClassVar

import casadi as ca
import numpy as np

from solver.config import ReconstructionConfig
from solver.motion import motion_function
from solver.reconstruct import reconstruct
from solver.refine import nlp as refine_nlp
from solver.refine.layout import Variant, block_parameters, node_parameters, node_scale

from .profiles import PROFILES
from .simulate import simulate
from .truth import load_truth, truth_names

NS, NU = 6, 6  # stage state and control sizes
ONE_RADAR = Variant()


@cache
def fatrop_block_solver(n: int, tol: float) -> ca.Function:
    """FATROP solver of the one-radar block NLP of ``n`` nodes; variables ``vec(Y)``, ``Y``
    ``(12, n)`` scaled as :func:`solver.refine.layout.node_scale`; parameters as IPOPT's."""
    v = Variant()
    P, E = node_parameters(v), block_parameters(v)
    sc = node_scale(v)  # x z phi v u w du+ du- dw+ dw-
    Y = ca.MX.sym("Y", NS + NU, n)
    X = ca.vertcat(Y[:4, :], Y[NS:, :]) * ca.repmat(ca.DM(sc), 1, n)
    Pm, Em = ca.MX.sym("P", P.size, n), ca.MX.sym("E", E.size)

    def row(name: str, k: int = 0) -> ca.MX:
        return Pm[P[name].start + k, :]

    x, z, u, w = X[0, :], X[1, :], X[4, :], X[5, :]
    dt = row("dt")
    nxt = motion_function().map(n - 1)(X[:4, : n - 1], u[: n - 1], w[: n - 1], dt[: n - 1])
    gap = Y[:NS, 1:] - ca.vertcat(nxt / ca.repmat(ca.DM(sc[:4]), 1, n - 1), Y[NS:NS + 2, : n - 1])
    change = ca.vertcat(Y[6, :] - Y[4, :] - Y[8, :] + Y[9, :],
                        Y[7, :] - Y[5, :] - Y[10, :] + Y[11, :])
    dx, dz = x - row("centre"), z - row("centre", 1)
    q = row("info") * dx * dx + 2 * row("info", 1) * dx * dz + row("info", 2) * dz * dz
    delta = Em[E["huber"]]
    cost = ca.sum2(row("weight") * 2 * delta**2 * (ca.sqrt(1 + q / delta**2) - 1))
    cost += ca.sum2(row("switch") * (X[6, :] + X[7, :]) + row("switch", 1) * (X[8, :] + X[9, :]))
    eps = Em[E["level_eps"]]
    cost += ca.sum2(dt * (Em[E["level_u"]] * row("level") * ca.sqrt(u * u + eps**2)
                          + Em[E["level_w"]] * row("level", 1) * ca.sqrt(w * w + eps**2)))
    g = ca.vertcat(ca.vec(ca.vertcat(gap, change[:, : n - 1])), change[:, n - 1])
    problem = {"x": ca.vec(Y), "p": ca.vertcat(ca.vec(Pm), Em), "f": cost, "g": g}
    opts = {"print_time": False, "error_on_fail": False, "structure_detection": "manual",
            "N": n - 1, "nx": [NS] * n, "nu": [NU] * n, "ng": [2] * n,
            "fatrop": {"print_level": 0, "tol": tol}}
    return ca.nlpsol(f"fatrop_block_{n}", "fatrop", problem, opts)


class FatropAsIpopt:
    """FATROP behind the IPOPT block solver's call: maps IPOPT's node layout (10 rows a node)
    to the stage layout (12) and back, and records each solve."""

    log: ClassVar[list[dict]] = []

    def __init__(self, n: int, tol: float, polish: bool):
        self.n, self.solver, self.polish = n, fatrop_block_solver(n, tol), polish
        self._stats: dict = {}

    def _stages(self, ipopt_x: np.ndarray, prev_uw: np.ndarray) -> np.ndarray:
        X = np.asarray(ipopt_x, dtype=float).reshape(self.n, 10)
        Y = np.empty((self.n, NS + NU))
        Y[:, :4], Y[:, NS:] = X[:, :4], X[:, 4:]
        Y[1:, 4:6], Y[0, 4:6] = X[:-1, 4:6], prev_uw
        return Y

    def __call__(self, x0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None) -> dict:
        E = block_parameters(Variant())
        extra = np.asarray(p, dtype=float).ravel()[-E.size:]
        prev = np.array([extra[E["u_prev"]][0], extra[E["w_prev"]][0]])
        lo, hi = self._stages(lbx, prev), self._stages(ubx, prev)
        lo[1:, 4:6], hi[1:, 4:6] = -np.inf, np.inf
        t0 = time.process_time()
        res = self.solver(x0=self._stages(x0, prev).ravel(), p=p, lbx=lo.ravel(),
                          ubx=hi.ravel(), lbg=0, ubg=0)
        cpu = time.process_time() - t0
        st = self.solver.stats()
        self.log.append({"polish": self.polish, "cpu_s": cpu, "iterations": st["iter_count"],
                         "success": bool(st["success"]),
                         "riccati_s": st["fatrop"]["compute_sd_time"]})
        self._stats = {"return_status": "fatrop", "iter_count": st["iter_count"],
                       "success": st["success"]}
        Ysol = np.array(res["x"]).reshape(self.n, NS + NU)
        x = np.concatenate([Ysol[:, :4], Ysol[:, NS:]], axis=1).ravel()
        return {"x": x, "lam_x": np.zeros(x.size), "lam_g": np.zeros(6 * self.n - 4)}

    def stats(self) -> dict:
        return self._stats


class TimedIpopt:
    """The committed IPOPT block solver, timed per solve."""

    log: ClassVar[list[dict]] = []

    def __init__(self, solver: ca.Function, polish: bool):
        self.solver, self.polish = solver, polish

    def __call__(self, **args) -> dict:
        t0 = time.process_time()
        res = self.solver(**args)
        cpu = time.process_time() - t0
        st = self.solver.stats()
        self.log.append({"polish": self.polish, "cpu_s": cpu, "iterations": st["iter_count"],
                         "success": bool(st["success"])})
        return res

    def stats(self) -> dict:
        return self.solver.stats()


def run(profile: str, tracks: int) -> dict:
    """Reconstruct the dev tracks (seed 100) with IPOPT, then with FATROP, after one warm-up
    pass each (solvers built); CPU seconds per pass and per solve, positions compared."""
    prof = PROFILES[profile]
    sims = [simulate(load_truth(name), prof, 100) for name in truth_names()[:tracks]]
    cfg = ReconstructionConfig()
    ipopt_block_solver = refine_nlp.block_solver
    out: dict = {"profile": profile, "tracks": tracks,
                 "plots": int(sum(s.plots.t.size for s in sims))}
    positions = {}
    def timed_ipopt(n, variant=ONE_RADAR, warm=False, tol=1e-6):
        return TimedIpopt(ipopt_block_solver(n, variant, warm, tol), warm)

    def fatrop(n, variant=ONE_RADAR, warm=False, tol=1e-6):
        assert variant == ONE_RADAR, "the probe states only the one-radar NLP"
        return FatropAsIpopt(n, tol, warm)

    for name, factory in (("ipopt", timed_ipopt), ("fatrop", fatrop)):
        refine_nlp.block_solver = factory  # type: ignore[assignment]
        try:
            for s in sims:
                reconstruct(s.plots, prof.radar(), cfg)
            log = TimedIpopt.log if name == "ipopt" else FatropAsIpopt.log
            log.clear()
            t0 = time.process_time()
            recs = [reconstruct(s.plots, prof.radar(), cfg) for s in sims]
            out[f"{name}_pass_cpu_s"] = time.process_time() - t0
            out[f"{name}_solves"] = list(log)
            positions[name] = np.concatenate(
                [np.column_stack([r.at_plots.x, r.at_plots.z]) for r in recs])
        finally:
            refine_nlp.block_solver = ipopt_block_solver
    d = np.hypot(*(positions["ipopt"] - positions["fatrop"]).T)
    out["position_diff_max_m"] = float(d.max())
    out["position_diff_rms_m"] = float(np.sqrt((d**2).mean()))
    return out


def report(r: dict) -> str:
    """Markdown summary of :func:`run`."""
    ip, fa = r["ipopt_solves"], r["fatrop_solves"]
    first_ip, polish_ip = ([e for e in ip if e["polish"] == p] for p in (False, True))
    first_fa, polish_fa = ([e for e in fa if e["polish"] == p] for p in (False, True))

    def tot(log: list[dict], key: str) -> float:
        return sum(e[key] for e in log)

    def line(label: str, a: object, b: object) -> str:
        return f"| {label} | {a} | {b} |"

    ok = (f"{sum(e['success'] for e in log)}/{len(log)}" for log in (ip, fa))
    lines = [
        f"profile {r['profile']}, {r['tracks']} dev tracks (seed 100), {r['plots']} plots",
        "",
        "| | IPOPT + MUMPS | FATROP (Riccati) |",
        "|---|---:|---:|",
        line("reconstruction pass, CPU s", f"{r['ipopt_pass_cpu_s']:.2f}",
             f"{r['fatrop_pass_cpu_s']:.2f}"),
        line("first solves: CPU s", f"{tot(first_ip, 'cpu_s'):.3f}",
             f"{tot(first_fa, 'cpu_s'):.3f}"),
        line("first solves: iterations", tot(first_ip, "iterations"),
             tot(first_fa, "iterations")),
        line("first solves: FATROP's Newton steps (Riccati), CPU s", "",
             f"{tot(first_fa, 'riccati_s'):.3f}"),
        line("polish solves: CPU s", f"{tot(polish_ip, 'cpu_s'):.3f}",
             f"{tot(polish_fa, 'cpu_s'):.3f}"),
        line("polish solves: iterations", tot(polish_ip, "iterations"),
             tot(polish_fa, "iterations")),
        line("solves reported successful", *ok),
        "",
        f"Positions at the plots, FATROP against IPOPT: max {r['position_diff_max_m']:.2f} m, "
        f"RMS {r['position_diff_rms_m']:.3f} m.",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="seed000", choices=sorted(PROFILES))
    ap.add_argument("--tracks", type=int, default=7)
    ap.add_argument("--out", default=None, help="write the markdown summary here too")
    a = ap.parse_args()
    text = report(run(a.profile, a.tracks))
    print(text)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
