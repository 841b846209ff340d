"""CasADi functions compiled to machine code when a C compiler is at hand.

CasADi evaluates an SX function in its virtual machine. Compiled from CasADi's generated C by the
system compiler (``jit`` with the ``shell`` plugin; every derivative CasADi derives from the
function is compiled the same way), the refinement NLP's constraint Jacobian and Lagrangian
Hessian evaluate 4x and 6x faster (7 -> 1.7 ms and 11.5 -> 1.8 ms per IPOPT iteration on a
1458-plot track) and the whole refinement 1.5x faster (1.36 s -> 0.90 s, identical iterates).

Compiling is the bulk of a fresh process's start: the warm-up's 12 functions take 3-4 s of
``cc`` (0.46 s interpreted). So the compiler runs behind a cache (``jitcc.sh``, like ccache):
objects keyed by the SHA-256 of their source, kept in :func:`cache_dir`, so only the first
process on a machine compiles (warm-up 4.6 s -> about 0.8 s afterwards, measured in fresh
processes). A process without a compiler still loads what the cache holds (the Docker image's
final stage).

The compiler is ``$CC`` or ``cc``; ``TRAJRECON_COMPILE=0`` (or no compiler and nothing cached, or
a compiler that fails) keeps the virtual machine, with the same results.
"""

from __future__ import annotations

import logging
import multiprocessing.util
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Sequence
from functools import cache, lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

LOG = logging.getLogger(__name__)
_COMPILED: set[str] = set()


@cache
def enabled() -> bool:
    """``TRAJRECON_COMPILE`` is not ``0`` (``false``, ``no``, ``off``); read once per process."""
    return os.environ.get("TRAJRECON_COMPILE", "1").strip().lower() not in ("0", "false", "no",
                                                                           "off")


@cache
def compiler() -> str | None:
    """Path of the C compiler to use, or None (disabled or not found)."""
    return shutil.which(os.environ.get("CC") or "cc") if enabled() else None


CACHE_ENV = "TRAJRECON_JIT_CACHE"
FRONT = Path(__file__).with_name("jitcc.sh")
STALE_S = 30 * 86400.0
"""Cache entries unused this long are removed (by the first process that compiles after)."""


@cache
def cache_dir() -> Path | None:
    """The compiled-object cache: ``$TRAJRECON_JIT_CACHE``, else ``$XDG_CACHE_HOME/trajrecon/jit``
    (``~/.cache/trajrecon/jit``), created private to the user; None if set to ``off`` (or
    ``0``, ``no``, ``false``, or empty) or if it cannot be created."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "no", "false"):
            return None
        path = Path(value).expanduser()
    else:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        path = Path(base) / "trajrecon" / "jit"
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as e:
        LOG.info("no compiled-object cache (%s): every process compiles", e)
        return None
    return path


def _prune(path: Path) -> None:
    """Remove the entries of ``path`` unused for :data:`STALE_S`: only where a compiler can
    rebuild them (never the compiler-less image's), and not in a read-only cache."""
    if not os.access(path, os.W_OK):
        return
    limit = time.time() - STALE_S
    for entry in path.iterdir():
        try:
            if entry.stat().st_mtime < limit:
                entry.unlink()
        except OSError:
            pass  # removed by another process meanwhile


@cache
def jit_command() -> str | None:
    """What CasADi's jit runs to compile and link: ``sh jitcc.sh CACHE MACHINE CC`` when there is
    a cache (``CC`` ``-`` without a compiler: the cache alone answers), the compiler alone
    when the cache cannot be used (no ``sh`` or ``sha256sum``, or a path with white space, which
    CasADi's command line would split); None: nothing can compile."""
    if not enabled():
        return None
    cc, cache_path = compiler(), cache_dir()
    words = [str(FRONT), str(cache_path), cc or "-"]
    if (cache_path is None or not shutil.which("sh") or not shutil.which("sha256sum")
            or any(len(w.split()) != 1 for w in words)):
        return cc
    if cc is None and not any(cache_path.glob("*.so")):
        return None
    if cc is not None:
        _prune(cache_path)
    return f"sh {FRONT} {cache_path} {platform.machine() or 'unknown'} {cc or '-'}"


PREFIX = "trajrecon-jit-"


@cache
def directory() -> str:
    """This process's directory for the generated C, removed when the process exits.

    CasADi deletes a function's source only when the function is destroyed, which a cached
    function never is in a pool worker (multiprocessing ends it with ``os._exit``): measured,
    every such process left its sources in the temporary directory. A multiprocessing finalizer
    runs at the exit of the main process and of every multiprocessing child alike; directories of
    processes that were killed (no finalizer) are removed by the next process that compiles.
    """
    _remove_orphans()
    path = tempfile.mkdtemp(prefix=f"{PREFIX}{os.getpid()}-")
    multiprocessing.util.Finalize(None, shutil.rmtree, args=(path, True), exitpriority=0)
    return path


def _remove_orphans() -> None:
    """Remove the directories of dead processes (``trajrecon-jit-<pid>-*``, ``pid`` not alive)."""
    for path in Path(tempfile.gettempdir()).glob(f"{PREFIX}*-*"):
        pid = path.name[len(PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(path, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def jit_options(cc: str) -> dict:
    """Options of :class:`casadi.Function` compiling it with the command ``cc`` (as
    :func:`jit_command`) in :func:`directory` (not the working directory, which may be
    read-only)."""
    return {"jit": True, "compiler": "shell", "jit_cleanup": False,
            "jit_options": {"compiler": cc, "linker": cc, "flags": ["-O1"], "cleanup": False,
                            "directory": directory(), "verbose": False}}


def function(name: str, inputs: Sequence[ca.SX], outputs: Sequence[ca.SX],
             input_names: Sequence[str], output_names: Sequence[str],
             derivatives: bool = True) -> ca.Function:
    """An SX :class:`casadi.Function`, compiled if :func:`jit_command` can compile it.

    The compiled function and (``derivatives``) its first derivatives are built (hence
    compiled) here, so a broken toolchain is found now and logged, not inside a solver later.
    """
    args = (name, list(inputs), list(outputs), list(input_names), list(output_names))
    cc = jit_command()
    if cc is not None:
        try:
            f = ca.Function(*args, jit_options(cc))
            if derivatives:
                f.forward(1)
                f.reverse(1)
            _COMPILED.add(name)
            return f
        except Exception as e:  # CasADi reports compiler and loader errors as RuntimeError
            LOG.warning("compiling %s with %s failed, interpreting it instead: %s", name, cc, e)
    return ca.Function(*args)


def is_compiled(name: str) -> bool:
    """Whether the function ``name`` built by :func:`function` runs compiled code."""
    return name in _COMPILED


MAP_SIZES = tuple(2**k for k in range(4, 13))  # column counts of the cached maps (16..4096)


@lru_cache(maxsize=64)
def _mapped(f: ca.Function, size: int) -> ca.Function:
    """``f.map(size)``, built once: a map costs 0.6-2 ms to build, as much as evaluating 350
    Jacobians of the motion model with it (a 350-plot refinement built three, one per call).
    Its buffer (13 us) is made per call, so threads never share one."""
    return f.map(size)


def evaluate_into(f: ca.Function, ins: Sequence[np.ndarray], outs: Sequence[np.ndarray]
                  ) -> None:
    """Evaluate ``f`` through :meth:`casadi.Function.buffer`, reading its inputs' nonzeros from
    the float arrays ``ins`` and writing its outputs' into ``outs`` (numpy memory directly: a
    ``DM`` result would go through a Python list, about 80 ns per element)."""
    buf, evaluate = f.buffer()
    for i, a in enumerate(ins):
        buf.set_arg(i, memoryview(a))
    for j, r in enumerate(outs):
        buf.set_res(j, memoryview(r))
    evaluate()
    if buf.ret() != 0:
        raise RuntimeError(f"evaluating {f.name()} failed (status {buf.ret()})")


def columns(f: ca.Function, *args: np.ndarray) -> list[np.ndarray]:
    """Evaluate ``f`` on every column of ``args`` (input ``i`` shaped ``(size_in(i), m)``):
    output ``j`` as a dense ``(m, *size_out(j))`` array.

    Through :meth:`casadi.Function.buffer` of a cached ``f.map(size)`` (``size`` from
    :data:`MAP_SIZES`: chunks of the largest, the rest padded by repeating its last column),
    which reads and writes numpy memory directly; calling ``f`` instead returns a ``DM`` whose
    conversion to numpy goes through a Python list (about 80 ns per element: 16 of the 21 ms of
    6000 Jacobians of the motion map).
    """
    m = args[0].shape[1]
    outs = [np.zeros((m, *f.size_out(j))) for j in range(f.n_out())]
    for i, a in enumerate(args):
        if not f.sparsity_in(i).is_dense() or a.shape != (f.size1_in(i), m):
            raise ValueError(f"input {i} of {f.name()}: expected a dense "
                             f"{f.size1_in(i)} x {m} array, got {a.shape}")
    for start in range(0, m, MAP_SIZES[-1]):
        stop = min(start + MAP_SIZES[-1], m)
        size = next(s for s in MAP_SIZES if s >= stop - start)
        pad = np.r_[start:stop, np.full(size - (stop - start), stop - 1)]
        ins = [np.asfortranarray(a[:, pad], dtype=float).reshape(-1, order="F") for a in args]
        nz = [np.empty(size * f.nnz_out(j)) for j in range(f.n_out())]
        evaluate_into(_mapped(f, size), ins, nz)
        for j, out in enumerate(outs):
            sp = f.sparsity_out(j)
            if sp.is_dense():  # column-major blocks: a reshape, no scatter
                out[start:stop] = nz[j].reshape(size, sp.size2(), sp.size1())[
                    : stop - start].transpose(0, 2, 1)
            else:
                out[start:stop, np.array(sp.row()), np.array(sp.get_col())] = \
                    nz[j].reshape(size, sp.nnz())[: stop - start]
    return outs
