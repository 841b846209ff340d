"""The solver keeps IPOPT's bundled OpenMP BLAS to one thread (``solver/__init__.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# A fresh interpreter: the variable only acts if set before IPOPT is first loaded.
PROBE = """
import os, sys, time
sys.path[:0] = [{root!r}, {tests!r}]
import solver
from tracks import make_track, SEED_RADAR
from solver.config import ReconstructionConfig
from solver.reconstruct import reconstruct
track = make_track(scan_s=4.0, sigma_r=50.0, sigma_psi=1e-3, drop_in_turns=False)
reconstruct(track.plots, SEED_RADAR, ReconstructionConfig())
w0, c0 = time.perf_counter(), time.process_time()
reconstruct(track.plots, SEED_RADAR, ReconstructionConfig())
print(os.environ["OMP_NUM_THREADS"], len(track.t), time.process_time() - c0,
      time.perf_counter() - w0)
"""


# Only the variable the import leaves (no solve: 5 s less).
IMPORT_ONLY = """
import os, sys
sys.path[:0] = [{root!r}]
import solver
print(os.environ["OMP_NUM_THREADS"])
"""


def _probe(env_extra: dict[str, str], probe: str = PROBE) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"} | env_extra
    code = probe.format(root=str(ROOT), tests=str(ROOT / "tests"))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300, check=True)
    return out.stdout.split()


def test_one_blas_thread_by_default_cpu_not_above_wall():
    threads, n, cpu, wall = _probe({})
    assert threads == "1"
    assert int(n) > 1000
    # with the second thread spinning, CPU time was twice the wall time (1.35 s wall, 2.6 s CPU)
    assert float(cpu) <= 1.2 * float(wall) + 0.05


def test_a_callers_choice_is_kept():
    assert _probe({"OMP_NUM_THREADS": "2"}, IMPORT_ONLY) == ["2"]
    assert _probe({}, IMPORT_ONLY) == ["1"]
