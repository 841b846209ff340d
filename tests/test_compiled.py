"""Compiled CasADi functions (solver.compiled): same numbers as the virtual machine, and a clean
fallback when compiling is off or impossible."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from solver import compiled
from solver.motion import motion_function, propagate_ca

ROOT = Path(__file__).resolve().parents[1]
needs_cc = pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler")


def _motion_pair(tmp_name: str) -> tuple[ca.Function, ca.Function]:
    s = ca.SX.sym("s", 4)
    u, w, t = ca.SX.sym("u"), ca.SX.sym("w"), ca.SX.sym("t")
    args = ([s, u, w, t], [propagate_ca(s, u, w, t)], ["state", "u", "w", "t"], ["state_t"])
    return compiled.function(tmp_name, *args), ca.Function("vm", *args)


@pytest.fixture
def fresh_compiler(monkeypatch):
    """Re-read the compiler choice from the (monkeypatched) environment."""
    compiled.compiler.cache_clear()
    yield monkeypatch
    compiled.compiler.cache_clear()


@needs_cc
def test_compiled_motion_and_derivatives_equal_the_virtual_machine():
    fc, fv = _motion_pair("motion_cmp")
    assert compiled.is_compiled("motion_cmp")
    rng = np.random.default_rng(3)
    n = 400
    state = np.vstack([rng.normal(0, 5e4, n), rng.normal(0, 5e4, n), rng.uniform(-4, 4, n),
                       rng.uniform(60, 300, n)])
    u, w, t = rng.uniform(-30, 30, n), rng.uniform(-5, 5, n), rng.uniform(0, 20, n)
    u[::4] = 0.0  # degenerate branches: straight, constant speed, both, zero time
    w[::3] = 0.0
    t[::7] = 0.0
    nominal = [state, u[None], w[None], t[None]]
    for derive in (lambda f: f, lambda f: f.jacobian(), lambda f: f.reverse(1),
                   lambda f: f.reverse(1).forward(1)):
        a, b = derive(fc), derive(fv)
        # the first four inputs of every derivative are the nominal ones; seeds are random
        ins = nominal + [rng.normal(size=(a.size1_in(i), a.size2_in(i) * n))
                         for i in range(4, a.n_in())]
        out_a, out_b = a.map(n).call(ins), b.map(n).call(ins)
        for xa, xb in zip(out_a, out_b, strict=True):
            xa, xb = np.array(xa), np.array(xb)
            assert np.all(np.isfinite(xb))
            np.testing.assert_allclose(xa, xb, rtol=1e-12, atol=1e-12 * (1 + np.abs(xb).max()))


def test_compile_off_keeps_the_virtual_machine(fresh_compiler):
    fresh_compiler.setenv("TRAJRECON_COMPILE", "0")
    assert compiled.compiler() is None
    f, g = _motion_pair("motion_off")
    assert not compiled.is_compiled("motion_off")
    np.testing.assert_array_equal(np.array(f([1e4, 2e4, 0.3, 150], 2.0, 0.5, 8.0)),
                                  np.array(g([1e4, 2e4, 0.3, 150], 2.0, 0.5, 8.0)))


def test_broken_compiler_falls_back_with_a_warning(fresh_compiler, tmp_path, caplog):
    cc = tmp_path / "cc"
    cc.write_text("#!/bin/sh\necho 'cc: out of order' >&2\nexit 1\n")
    cc.chmod(0o755)
    fresh_compiler.setenv("CC", str(cc))
    fresh_compiler.delenv("TRAJRECON_COMPILE", raising=False)
    assert compiled.compiler() == str(cc)
    with caplog.at_level(logging.WARNING, logger="solver.compiled"):
        f, g = _motion_pair("motion_broken")
    assert not compiled.is_compiled("motion_broken")
    assert "interpreting it instead" in caplog.text
    np.testing.assert_array_equal(np.array(f([1e4, 2e4, 0.3, 150], 2.0, 0.5, 8.0)),
                                  np.array(g([1e4, 2e4, 0.3, 150], 2.0, 0.5, 8.0)))


_REFINE = """
import json, numpy as np
from solver import compiled
from solver.config import ReconstructionConfig
from solver.reconstruct import reconstruct
from solver.warmup import synthetic_track
plots, radar = synthetic_track(120)
rng = np.random.default_rng(0)
plots = type(plots).from_arrays(plots.t, plots.range_m + rng.normal(0, 150, plots.t.size),
                                plots.azimuth_rad + rng.normal(0, 0.003, plots.t.size))
rec = reconstruct(plots, radar, ReconstructionConfig())
print(json.dumps({"compiled": compiled.is_compiled("motion"), "x": rec.at_plots.x.tolist(),
                  "z": rec.at_plots.z.tolist(),
                  "iterations": rec.diagnostics.extra["refine_iterations"]}))
"""


def _refine_in_subprocess(compile_flag: str) -> dict:
    env = {**os.environ, "TRAJRECON_COMPILE": compile_flag, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", _REFINE], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=300, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


@needs_cc
def test_refinement_is_the_same_compiled_or_interpreted():
    on, off = _refine_in_subprocess("1"), _refine_in_subprocess("0")
    assert on["compiled"] and not off["compiled"]
    assert on["iterations"] == off["iterations"]
    np.testing.assert_allclose(on["x"], off["x"], atol=1e-6)
    np.testing.assert_allclose(on["z"], off["z"], atol=1e-6)


def test_the_motion_model_in_use_is_compiled_when_a_compiler_exists():
    motion_function()
    assert compiled.is_compiled("motion") == (compiled.compiler() is not None)


_POOL = """
import os
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor


def work():
    from solver import compiled
    from solver.motion import motion_function
    motion_function()
    d = compiled.directory()
    assert os.listdir(d)  # the generated C is there while the process lives
    return d


if __name__ == "__main__":
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        child = ex.submit(work).result()
    print(child, os.path.exists(child))
    print(work())
"""


@needs_cc
def test_generated_sources_are_removed_when_processes_exit(tmp_path):
    """Pool workers end by ``os._exit`` (no destructors, no atexit): their directory must still
    go, and so must the main process's."""
    script = tmp_path / "pool.py"
    script.write_text(_POOL)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, str(script)], env=env, cwd=tmp_path, capture_output=True,
                       text=True, timeout=300, check=True)
    (child, child_exists), (main,) = (line.split() for line in r.stdout.strip().splitlines())
    assert child_exists == "False", child
    assert not Path(main).exists(), main
    assert "trajrecon-jit-" in main and "Failed to remove" not in r.stderr


def test_directories_of_killed_processes_are_removed_by_the_next(tmp_path, monkeypatch):
    """A killed process runs no finalizer; the next process that compiles removes its directory
    (named after its pid), and never one of a live process."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    orphan = tmp_path / f"{compiled.PREFIX}{dead.stdout.strip()}-abc"
    live = tmp_path / f"{compiled.PREFIX}{os.getpid()}-def"
    other = tmp_path / "someone-else"
    for d in (orphan, live, other):
        d.mkdir()
        (d / "jit_tmp.c").write_text("int x;\n")
    compiled._remove_orphans()
    assert not orphan.exists()
    assert live.exists() and other.exists()


def test_columns_equals_column_by_column_calls():
    """``compiled.columns`` (numpy buffers) against CasADi's own per-column calls, with a sparse
    output (the motion Jacobian has 18 of 36 entries structurally non-zero) and a second output."""
    s, dt = ca.SX.sym("s", 6), ca.SX.sym("dt")
    out = ca.vertcat(motion_function()(s[:4], s[4], s[5], dt), s[4], s[5])
    f = ca.Function("cols", [s, dt], [ca.jacobian(out, s), out])
    assert not f.sparsity_out(0).is_dense()
    rng = np.random.default_rng(5)
    # 50: one padded map; 4096: one whole map; 4096 + 17: a whole map and a padded one
    for m in (50, compiled.MAP_SIZES[-1], compiled.MAP_SIZES[-1] + 17):
        S = np.vstack([rng.normal(0, 5e4, (2, m)), rng.uniform(-4, 4, (1, m)),
                       rng.uniform(60, 300, (1, m)), rng.uniform(-30, 30, (1, m)),
                       rng.uniform(-5, 5, (1, m))])
        S[4, ::5] = 0.0
        T = rng.uniform(0, 20, (1, m))
        jac, val = compiled.columns(f, S, T)
        assert jac.shape == (m, 6, 6) and val.shape == (m, 6, 1)
        for k in range(m):
            j_ref, v_ref = f(S[:, k], T[0, k])
            np.testing.assert_array_equal(jac[k], np.array(j_ref))
            np.testing.assert_array_equal(val[k], np.array(v_ref))
    empty = compiled.columns(f, S[:, :0], T[:, :0])
    assert empty[0].shape == (0, 6, 6)
    with pytest.raises(ValueError, match="input 1"):
        compiled.columns(f, S, T[:, :-1])
