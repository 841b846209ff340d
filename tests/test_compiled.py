"""Compiled CasADi functions (solver.compiled): same numbers as the virtual machine, and a clean
fallback when compiling is off or impossible."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import tempfile
import time
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


_CHOICES = (compiled.enabled, compiled.compiler, compiled.cache_dir, compiled.jit_command)


@pytest.fixture
def fresh_compiler(monkeypatch):
    """Re-read the compiler and cache choices from the (monkeypatched) environment."""
    for f in _CHOICES:
        f.cache_clear()
    yield monkeypatch
    for f in _CHOICES:
        f.cache_clear()


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


def test_compile_off_keeps_the_virtual_machine(fresh_compiler, tmp_path):
    fresh_compiler.setenv("TRAJRECON_COMPILE", "0")
    fresh_compiler.setenv(compiled.CACHE_ENV, str(tmp_path))
    (tmp_path / "0123.so").write_bytes(b"")  # a cache with entries does not turn it on
    assert compiled.compiler() is None and compiled.jit_command() is None
    f, g = _motion_pair("motion_off")
    assert not compiled.is_compiled("motion_off")
    np.testing.assert_array_equal(np.array(f([1e4, 2e4, 0.3, 150], 2.0, 0.5, 8.0)),
                                  np.array(g([1e4, 2e4, 0.3, 150], 2.0, 0.5, 8.0)))


def test_broken_compiler_falls_back_with_a_warning(fresh_compiler, tmp_path, caplog):
    cc = tmp_path / "cc"
    cc.write_text("#!/bin/sh\necho 'cc: out of order' >&2\nexit 1\n")
    cc.chmod(0o755)
    fresh_compiler.setenv("CC", str(cc))
    fresh_compiler.setenv(compiled.CACHE_ENV, str(tmp_path / "cache"))  # empty: nothing to load
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


def _refine_in_subprocess(compile_flag: str, **extra: str) -> dict:
    env = {**os.environ, "TRAJRECON_COMPILE": compile_flag, "PYTHONPATH": str(ROOT), **extra}
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
    assert compiled.is_compiled("motion") == (compiled.jit_command() is not None)


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


# ------------------------------------------------------------------ the compiled-object cache

_COMPILE_MOTION = """
import json, numpy as np
from solver import compiled
from solver.motion import motion_function
f = motion_function()
h = f.reverse(1).forward(1)  # a second derivative, as IPOPT's Hessian asks for
x = {"state": [1e4, 2e4, 0.3, 150.0], "u": 2.0, "w": 0.5, "t": 8.0}
seeds = {"adj_state_t": [0.1, -0.2, 0.3, 0.4], "fwd_state": [1.0, 2.0, 0.01, 3.0], "fwd_u": 0.1,
         "fwd_w": -0.2, "fwd_t": 0.5}
print(json.dumps({"compiled": compiled.is_compiled("motion"), "command": compiled.jit_command(),
                  "f": np.array(f(*x.values())).ravel().tolist(),
                  "h": np.array(h(**x, **seeds)["fwd_adj_state"]).ravel().tolist()}))
"""


def _counting_cc(tmp_path: Path) -> tuple[Path, Path]:
    """A compiler that appends each command line to a log, then runs the real one."""
    log, cc = tmp_path / "cc.log", tmp_path / "counting-cc"
    cc.write_text(f"#!/bin/sh\necho \"$*\" >> {log}\nexec {compiled.compiler()} \"$@\"\n")
    cc.chmod(0o755)
    return cc, log


def _motion_in_subprocess(env: dict) -> dict:
    r = subprocess.run([sys.executable, "-c", _COMPILE_MOTION], cwd=ROOT, capture_output=True,
                       text=True, timeout=300, check=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT), **env})
    return json.loads(r.stdout.strip().splitlines()[-1])


@needs_cc
def test_a_second_process_loads_the_cache_and_compiles_nothing(tmp_path):
    cc, log = _counting_cc(tmp_path)
    cache = tmp_path / "cache"
    first = _motion_in_subprocess({"CC": str(cc), compiled.CACHE_ENV: str(cache)})
    compiles = log.read_text().splitlines()
    assert first["compiled"] and "jitcc.sh" in first["command"]
    assert sum(" -c " in c for c in compiles) >= 4  # the function and three derivatives
    assert len(list(cache.glob("*.o"))) >= 4 and len(list(cache.glob("*.so"))) >= 4
    again = _motion_in_subprocess({"CC": str(cc), compiled.CACHE_ENV: str(cache)})
    assert log.read_text().splitlines() == compiles, "the second process compiled"
    # no compiler at all (the Docker image's final stage): the cache alone
    alone = _motion_in_subprocess({"CC": str(tmp_path / "missing-cc"),
                                   compiled.CACHE_ENV: str(cache)})
    assert alone["compiled"] and alone["command"].endswith(" -")
    off = _motion_in_subprocess({"TRAJRECON_COMPILE": "0", compiled.CACHE_ENV: str(cache)})
    assert not off["compiled"]
    for run in (again, alone):
        assert run["f"] == first["f"] and run["h"] == first["h"]
    np.testing.assert_allclose(first["f"], off["f"], rtol=1e-13)
    np.testing.assert_allclose(first["h"], off["h"], rtol=1e-12, atol=1e-12)


_C = "double f(double x) {{ return {} * x; }}\n"


def _front(cache: Path, cc: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["sh", str(compiled.FRONT), str(cache), "x86_64", cc, *args],
                          capture_output=True, text=True, timeout=60)


@needs_cc
def test_the_cache_key_is_the_source_and_the_flags_not_the_paths(tmp_path):
    cc, log = _counting_cc(tmp_path)
    cache = tmp_path / "cache"
    cache.mkdir()

    def compile_(text: str, name: str, *flags: str) -> bytes:
        src = tmp_path / f"{name}.c"
        src.write_text(text)
        obj = Path(str(src) + ".o")
        obj.touch(mode=0o600)  # as CasADi's output files, made by mkstemp
        r = _front(cache, str(cc), *flags, "-fPIC", "-c", str(src), "-o", str(obj))
        assert r.returncode == 0, r.stderr
        return Path(str(src) + ".o").read_bytes()

    a = compile_(_C.format(2.0), "a", "-O1")
    assert compile_(_C.format(2.0), "b", "-O1") == a  # same source elsewhere: from the cache
    assert len(log.read_text().splitlines()) == 1
    compile_(_C.format(3.0), "c", "-O1")  # another source
    compile_(_C.format(2.0), "d", "-O2")  # other flags
    assert len(log.read_text().splitlines()) == 3
    assert len(list(cache.glob("*.o"))) == 3 and not list(cache.glob(".tmp.*"))
    # readable by other users (the Docker image compiles as root and runs as another user),
    # though CasADi writes its objects 0600
    assert all(e.stat().st_mode & 0o444 == 0o444 for e in cache.iterdir())


@needs_cc
def test_a_failed_compile_is_not_cached_and_no_compiler_misses_cleanly(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    src = tmp_path / "bad.c"
    src.write_text("this is not C\n")
    r = _front(cache, compiled.compiler(), "-O1", "-c", str(src), "-o", str(tmp_path / "bad.o"))
    assert r.returncode != 0 and not any(cache.iterdir())
    src.write_text(_C.format(4.0))
    r = _front(cache, "-", "-O1", "-c", str(src), "-o", str(tmp_path / "x.o"))
    assert r.returncode == 1 and "not in" in r.stderr and "no compiler" in r.stderr


@needs_cc
def test_concurrent_processes_fill_the_cache_whole(tmp_path):
    """Eight fronts compile the same source at once (workers starting together): each gets a
    whole object and the cache holds one whole entry, no temporary file."""
    cache = tmp_path / "cache"
    cache.mkdir()
    src = tmp_path / "same.c"
    src.write_text(_C.format(5.0))
    procs = [subprocess.Popen(["sh", str(compiled.FRONT), str(cache), "x86_64",
                               compiled.compiler(), "-O1", "-fPIC", "-c", str(src), "-o",
                               str(tmp_path / f"out{i}.o")], stderr=subprocess.PIPE)
             for i in range(8)]
    assert all(p.wait(timeout=60) == 0 for p in procs)
    objects = {(tmp_path / f"out{i}.o").read_bytes() for i in range(8)}
    (entry,) = cache.iterdir()
    assert objects == {entry.read_bytes()} and entry.suffix == ".o"


def test_stale_entries_are_pruned_only_where_a_compiler_can_rebuild(fresh_compiler, tmp_path):
    fresh_compiler.setenv(compiled.CACHE_ENV, str(tmp_path))
    fresh_compiler.delenv("TRAJRECON_COMPILE", raising=False)
    old, new = tmp_path / "old.so", tmp_path / "new.so"
    for f in (old, new):
        f.write_bytes(b"\x7fELF")
    stale = time.time() - compiled.STALE_S - 3600
    os.utime(old, (stale, stale))
    fresh_compiler.setenv("CC", str(tmp_path / "missing-cc"))  # no compiler: nothing removed
    assert compiled.jit_command().endswith(" -")
    assert old.exists()
    for f in _CHOICES:
        f.cache_clear()
    fresh_compiler.setenv("CC", "/bin/true")  # stands for a compiler; nothing is compiled here
    assert compiled.jit_command().endswith(" /bin/true")
    assert not old.exists() and new.exists()


def test_cache_off_or_unusable_compiles_every_time(fresh_compiler, tmp_path):
    fresh_compiler.delenv("TRAJRECON_COMPILE", raising=False)
    fresh_compiler.setenv("CC", "/bin/true")  # stands for a compiler; nothing is compiled here
    fresh_compiler.setenv(compiled.CACHE_ENV, "off")
    assert compiled.cache_dir() is None and compiled.jit_command() == "/bin/true"
    for f in _CHOICES:
        f.cache_clear()
    blocked = tmp_path / "file"
    blocked.write_text("")
    fresh_compiler.setenv(compiled.CACHE_ENV, str(blocked / "cache"))  # cannot be created
    assert compiled.cache_dir() is None and compiled.jit_command() == "/bin/true"
    for f in _CHOICES:
        f.cache_clear()
    fresh_compiler.delenv(compiled.CACHE_ENV)
    fresh_compiler.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compiled.cache_dir() == tmp_path / "xdg" / "trajrecon" / "jit"
    assert compiled.cache_dir().stat().st_mode & 0o777 == 0o700


@needs_cc
def test_a_cache_without_the_solvers_derivatives_and_no_compiler_interprets_them(tmp_path):
    """A cache filled by a process that built the motion model alone, then no compiler: the
    refinement's solvers fall back to the interpreted model (a warning), not to the sliding
    windows, and give the interpreted answer."""
    cache = tmp_path / "cache"
    _motion_in_subprocess({compiled.CACHE_ENV: str(cache)})
    partial = _refine_in_subprocess("1", CC=str(tmp_path / "missing-cc"),
                                    **{compiled.CACHE_ENV: str(cache)})
    off = _refine_in_subprocess("0")
    assert partial["compiled"]  # the model itself came from the cache
    assert partial["iterations"] == off["iterations"]
    np.testing.assert_allclose(partial["x"], off["x"], atol=1e-6)
    np.testing.assert_allclose(partial["z"], off["z"], atol=1e-6)
