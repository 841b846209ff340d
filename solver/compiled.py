"""CasADi functions compiled to machine code when a C compiler is at hand.

CasADi evaluates an SX function in its virtual machine. Compiled from CasADi's generated C by the
system compiler (``jit`` with the ``shell`` plugin; every derivative CasADi derives from the
function is compiled the same way), the refinement NLP's constraint Jacobian and Lagrangian
Hessian evaluate 4x and 6x faster (7 -> 1.7 ms and 11.5 -> 1.8 ms per IPOPT iteration on a
1458-plot track) and the whole refinement 1.5x faster (1.36 s -> 0.90 s, identical iterates).
Compiling takes about 0.1 s per function, once per process.

The compiler is ``$CC`` or ``cc``; ``TRAJRECON_COMPILE=0`` (or no compiler, or a compiler that
fails) keeps the virtual machine, with the same results.
"""

from __future__ import annotations

import logging
import multiprocessing.util
import os
import shutil
import tempfile
from collections.abc import Sequence
from functools import cache, lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

LOG = logging.getLogger(__name__)
_COMPILED: set[str] = set()


@cache
def compiler() -> str | None:
    """Path of the C compiler to use, or None (disabled or not found)."""
    if os.environ.get("TRAJRECON_COMPILE", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    return shutil.which(os.environ.get("CC") or "cc")


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
    """Options of :class:`casadi.Function` compiling it with ``cc`` in :func:`directory` (not the
    working directory, which may be read-only)."""
    return {"jit": True, "compiler": "shell", "jit_cleanup": False,
            "jit_options": {"compiler": cc, "linker": cc, "flags": ["-O1"], "cleanup": False,
                            "directory": directory(), "verbose": False}}


def function(name: str, inputs: Sequence[ca.SX], outputs: Sequence[ca.SX],
             input_names: Sequence[str], output_names: Sequence[str]) -> ca.Function:
    """An SX :class:`casadi.Function`, compiled if :func:`compiler` gives a working compiler.

    The compiled function and its first derivatives are built (hence compiled) here, so a
    broken toolchain is found now and logged, not inside a solver later.
    """
    args = (name, list(inputs), list(outputs), list(input_names), list(output_names))
    cc = compiler()
    if cc is not None:
        try:
            f = ca.Function(*args, jit_options(cc))
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
