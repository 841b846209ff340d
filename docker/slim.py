#!/usr/bin/env python3
"""Shrink a virtual environment's site-packages for the image, and check what is left.

``slim.py SITE_PACKAGES`` (after the locked install, which runs with ``--no-compile``):

- Wheels cannot hold symbolic links, so a shared library shipped as ``libx.so``,
  ``libx.so.3`` and ``libx.so.3.7`` is three copies (casadi, pyarrow...), and the same
  auditwheel-grafted ``libgfortran`` sits in numpy.libs, scipy.libs and casadi: every copy
  after the first becomes a relative symbolic link to it (53 MB on the locked set, counted
  after the removals below, which run first).
- Test suites that packages ship inside themselves (``numpy/*/tests``, ``scipy/**/tests``,
  ``pyarrow/tests``: 31 MB without their .pyc) are removed; nothing imports them at run time.
- What the product never loads (``DROP``, found by recording every shared object the
  processes of ``--check`` load, ``LD_DEBUG=files``): CasADi's plugins but those it uses
  (``CASADI_PLUGINS``: ``ipopt``, ``sqpmethod`` with ``qrqp``, the jit's ``importer_shell``)
  and then every third-party library in ``casadi/`` that no kept plugin needs (HiGHS, the COIN
  MILP stack, alpaqa, fatrop/blasfeo, uno, ONNX, Modelica...); their headers, CMake files and
  static archives; pyarrow's Flight and S3 extensions and their libraries (``pyarrow.fs``
  imports S3 behind an ``ImportError`` guard; Flight is a module of its own); every SciPy
  subpackage but ``scipy.linalg``, the only one the product imports (``expm``,
  ``solveh_banded``), and ``import scipy.linalg`` imports no other (``SCIPY_GONE`` lists the
  few functions of ``scipy.linalg`` that import one lazily, and so no longer work); Pillow's
  extensions but the core ``_imaging`` (AVIF, WebP, Tk, colour management, fonts: matplotlib
  draws text with its own FreeType) and the libraries only they need; the Swagger UI source
  maps and ES-module builds (the docs page loads ``swagger-ui-bundle.js`` and
  ``swagger-ui.css``); C sources, headers, Cython sources and type stubs shipped beside
  compiled code; numpy's and pyarrow's compiled test modules.
- Symbol tables of the shared objects (``strip --strip-unneeded``, when binutils is there;
  the wheels ship most of them unstripped).

``slim.py --check DIR`` runs what the image runs on what is left, and fails (so the image's
build fails) if any part no longer works: see :func:`check`. Run it with bytecode writing on
(``PYTHONDONTWRITEBYTECODE=``): the ``.pyc`` files it leaves are then exactly the modules the
image imports (39 MB, against 84 MB for every module, which pip's compile step would write).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

# The CasADi plugins the product loads (solver/window.py, solver/refine/nlp.py: nlpsol ipopt,
# and sqpmethod with the qrqp QP solver; solver/compiled.py: the jit through importer_shell and
# filesystem_ghc), and the small linear-solver plugins those may ask for; every other
# libcasadi_<plugin>.so goes, and then the third-party libraries only those needed.
CASADI_PLUGINS = re.compile(r"libcasadi_(nlpsol_ipopt|nlpsol_sqpmethod|conic_qrqp|"
                            r"importer_shell|filesystem_ghc|linsol_\w+)\.so.*")
DROP = (
    "casadi/include", "casadi/cmake", "casadi/pkgconfig", "casadi/cbc", "casadi/clp",
    "casadi/highs", "casadi/casadi-cli",
    "pyarrow/_flight*.so", "pyarrow/flight.py", "pyarrow/_s3fs*.so", "pyarrow/include",
    "pyarrow/src", "pyarrow/includes",
    # every SciPy subpackage but scipy.linalg (and its helpers in _lib): see SCIPY_GONE
    *(f"scipy/{p}" for p in ("cluster", "datasets", "differentiate", "fft", "fftpack",
                            "integrate", "interpolate", "io", "misc", "ndimage", "odr",
                            "optimize", "signal", "sparse", "spatial", "special", "stats")),
    # Pillow's AVIF, WebP, Tk, colour-management, font, math and morphology extensions
    # (matplotlib writes PNG with PIL.Image and draws text with its own FreeType)
    "PIL/_avif*.so", "PIL/_webp*.so", "PIL/_imagingtk*.so", "PIL/_imagingcms*.so",
    "PIL/_imagingft*.so", "PIL/_imagingmath*.so", "PIL/_imagingmorph*.so",
    # (not numpy/f2py: scipy.linalg imports it, through array_api_compat's "from numpy import *")
    # the docs page loads swagger-ui-bundle.js and swagger-ui.css: not the source maps, nor
    # the ES-module builds
    "swagger_ui_bundle/**/*.map", "swagger_ui_bundle/**/swagger-ui-es-bundle*.js",
    # sources, headers and stubs of compiled code, static archives, compiled-in test modules
    "**/*.c", "**/*.h", "**/*.pyx", "**/*.pxd", "**/*.pxi", "**/*.pyi", "**/*.a", "**/*.la",
    "numpy/_core/_*_tests.*.so", "pyarrow/_pyarrow_cpp_tests.*.so",
)
# Directories whose shared libraries are kept only while something left needs them, and the
# extensions (or CasADi plugins) they are needed from: ``prune_libraries``.
LIBRARY_DIRS = {"casadi": ("casadi/_casadi*.so", "casadi/libcasadi*.so*"),
                "pyarrow": ("pyarrow/*.cpython-*.so",),
                "pillow.libs": ("PIL/*.so",)}
# scipy.linalg functions that import a removed subpackage when called; the product uses none
SCIPY_GONE = ("logm", "fractional_matrix_power", "clarkson_woodruff_transform", "pascal",
              "invpascal", "matmul_toeplitz", "interpolative")
ELF = b"\x7fELF"


def digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def size(path: Path) -> int:
    if path.is_symlink() or not path.exists():
        return 0
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def remove(path: Path) -> int:
    saved = size(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()
    return saved


def link_duplicates(site: Path, min_size: int = 100_000) -> int:
    """Replace identical files by relative symbolic links to one of them; bytes saved."""
    groups: dict[int, list[Path]] = defaultdict(list)
    for path in site.rglob("*"):
        if path.is_file() and not path.is_symlink() and path.stat().st_size >= min_size:
            groups[path.stat().st_size].append(path)
    saved = 0
    for size_, paths in groups.items():
        if len(paths) < 2:
            continue
        by_hash: dict[str, list[Path]] = defaultdict(list)
        for path in paths:
            by_hash[digest(path)].append(path)
        for same in by_hash.values():
            keep, *copies = sorted(same, key=lambda p: (len(p.parts), len(p.name), str(p)))
            for copy in copies:
                copy.unlink()
                os.symlink(os.path.relpath(keep, copy.parent), copy)
                saved += size_
    return saved


def remove_tests(site: Path) -> int:
    """Remove ``tests`` directories inside installed packages; bytes saved."""
    saved = 0
    for path in sorted(site.glob("*/**/tests"), key=lambda p: len(p.parts)):
        if path.is_dir() and not path.is_symlink() and path.exists():
            saved += remove(path)
    return saved


def remove_unused(site: Path) -> int:
    """Remove ``DROP``, then the libraries of ``LIBRARY_DIRS`` that nothing left needs."""
    saved = sum(remove(p) for p in sorted(site.glob("casadi/libcasadi_*.so*"))
                if not CASADI_PLUGINS.fullmatch(p.name))
    for pattern in DROP:
        for path in sorted(site.glob(pattern), key=lambda p: len(p.parts)):
            if path.exists() or path.is_symlink():
                saved += remove(path)
    for libdir, roots in LIBRARY_DIRS.items():
        saved += prune_libraries(site / libdir, [p for g in roots for p in site.glob(g)])
    return saved


def needed(path: Path) -> list[str]:
    """The ``DT_NEEDED`` names of an ELF shared object (via ``readelf``, else ``ldd``)."""
    tool = shutil.which("readelf")
    if tool:
        out = subprocess.run([tool, "-d", str(path)], capture_output=True, text=True).stdout
        return re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", out)
    out = subprocess.run(["ldd", str(path)], capture_output=True, text=True).stdout
    return re.findall(r"^\s*(\S+) =>", out, re.M)


def prune_libraries(libdir: Path, roots: list[Path]) -> int:
    """Remove the shared libraries of ``libdir`` that ``roots`` do not need, directly or
    through each other (by name, through symbolic links); bytes saved."""
    if not libdir.is_dir():
        return 0
    libs = {p.name: p for p in libdir.iterdir() if ".so" in p.name and p.is_file()}
    keep: set[str] = set()
    todo: list[Path | str] = list(roots)
    while todo:
        item = todo.pop()
        if isinstance(item, str):  # a library's name, in libdir or not ours
            if item in keep or item not in libs:
                continue
            keep.add(item)
            item = libs[item]
        if item.is_symlink():
            todo.append(os.readlink(item))
        else:
            todo.extend(needed(item))
    return sum(remove(libs[n]) for n in sorted(set(libs) - keep - {r.name for r in roots}))


def loadable(path: Path) -> bool:
    """Whether the ELF64 file's loadable segments are as the dynamic loader requires (offset
    and address congruent modulo the alignment, inside the file). ``strip`` can break this in
    libraries that auditwheel's patchelf rewrote (numpy.libs' OpenBLAS: "ELF load command
    address/offset not page-aligned"); such a file keeps its symbols."""
    data = path.read_bytes()
    if data[:4] != ELF or data[4] != 2 or data[5] != 1:  # 64-bit little-endian only
        return False
    phoff = int.from_bytes(data[0x20:0x28], "little")
    phentsize = int.from_bytes(data[0x36:0x38], "little")
    for i in range(int.from_bytes(data[0x38:0x3A], "little")):
        h = data[phoff + i * phentsize: phoff + (i + 1) * phentsize]
        if int.from_bytes(h[0:4], "little") != 1:  # PT_LOAD
            continue
        offset, vaddr = int.from_bytes(h[8:16], "little"), int.from_bytes(h[16:24], "little")
        filesz, align = int.from_bytes(h[32:40], "little"), int.from_bytes(h[48:56], "little")
        if (align > 1 and (offset - vaddr) % align) or offset + filesz > len(data):
            return False
    return True


def strip_shared_objects(site: Path) -> int:
    """``strip --strip-unneeded`` every ELF shared object (not links) whose stripped copy is
    :func:`loadable`; bytes saved (0 without binutils)."""
    tool = shutil.which("strip")
    if tool is None:
        return 0
    saved = 0
    for path in sorted(site.rglob("*.so*")):
        if path.is_symlink() or not path.is_file() or not loadable(path):
            continue
        tmp = path.with_name(path.name + ".stripped")
        r = subprocess.run([tool, "--strip-unneeded", "-o", str(tmp), str(path)],
                           capture_output=True)
        if r.returncode == 0 and loadable(tmp) and tmp.stat().st_size < path.stat().st_size:
            saved += path.stat().st_size - tmp.stat().st_size
            shutil.copymode(path, tmp)
            os.replace(tmp, path)
        else:
            tmp.unlink(missing_ok=True)
    return saved


def slim(site: Path) -> None:
    # removals first, so that no link made next points at a file removed afterwards
    steps = (("test suites removed", remove_tests), ("never loaded, removed", remove_unused),
             ("duplicate files linked", link_duplicates),
             ("symbols stripped", strip_shared_objects))
    print("slim: " + ", ".join(f"{step(site) / 1e6:.0f} MB {what}" for what, step in steps))


CHECK_SENSORS = [{"id": "R1", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0,
                  "height_m": 300.0, "range_error_m": 150.0, "azimuth_error_deg": 0.24}]


def check(work: Path) -> None:
    """What the image runs, on what is left after slimming; raises if any part no longer works.

    Every module of the package, and the SciPy functions it calls; the service's warm-up with
    the ``ipopt`` NLP plugin (the service's own warm-up below runs ``sqpmethod`` with ``qrqp``;
    both run the sliding windows and the refinement); the command line end to end on a small
    CSV plot table (two aircraft, one radar) on a one-worker Dask ``LocalCluster`` with
    ``--figures``: Parquet, CSV and GeoJSON written, the Parquet read back, the map and the
    figures as PNG (matplotlib, Agg); then the service itself (``python -m service``, one
    worker, no compiler): ``/readyz``, ``/docs`` and its script from the image, and one
    reconstruction answered 200.
    """
    import importlib
    import json
    import pkgutil

    import numpy as np
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq
    import scipy.linalg

    import service
    import solver

    for pkg in (solver, service):
        for mod in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            if mod.name != "service.__main__":
                importlib.import_module(mod.name)
    # what the product calls of SciPy (solver.estimation), on what is left of it
    assert np.allclose(scipy.linalg.expm(np.diag([0.0, 1.0])), np.diag([1.0, np.e]))
    banded = scipy.linalg.solveh_banded(np.array([[0.0, 1.0], [4.0, 4.0]]), np.ones(2))
    assert np.allclose(banded, [0.2, 0.2]), banded
    from service.workers import warm_up
    from solver.cli import main as cli
    from solver.warmup import synthetic_track

    warm_up([3], "ipopt")  # sqpmethod: the Dockerfile's warm-up before, the service's below

    # two straight tracks seen by R1 every 4 s (range, and azimuth from north)
    t = 4.0 * np.arange(30.0)
    cols: dict[str, list] = {"t": [], "sensor": [], "range_m": [], "azimuth_deg": [],
                             "aircraft": []}
    for key, (x0, y0, vx, vy) in {"A1": (20e3, 40e3, 180.0, -60.0),
                                  "A2": (-30e3, 25e3, 150.0, 120.0)}.items():
        x, y = x0 + vx * t, y0 + vy * t
        cols["t"] += list(t)
        cols["sensor"] += ["R1"] * len(t)
        cols["range_m"] += list(np.hypot(x, y))
        cols["azimuth_deg"] += list(np.degrees(np.arctan2(x, y)) % 360)
        cols["aircraft"] += [key] * len(t)
    work.mkdir(parents=True, exist_ok=True)
    pacsv.write_csv(pa.table(cols), work / "plots.csv")
    (work / "sensors.json").write_text(json.dumps(CHECK_SENSORS))
    out = work / "out"
    code = cli([str(work / "plots.csv"), "--sensors", str(work / "sensors.json"), "--out",
                str(out), "--workers", "1", "--no-progress", "--figures"])
    summary = json.loads((out / "summary.json").read_text())
    assert code == 0 and summary["done"] == 2 and summary["failed"] == 0, summary
    assert pq.read_table(out / "tracks.parquet").num_rows == 60
    assert (out / "tracks.csv").read_text().count("\n") == 61
    pngs = [out / "map.png", *(out / "figures").glob("*.png")]
    assert len(pngs) == 3 and all(p.read_bytes().startswith(b"\x89PNG") for p in pngs), pngs

    plots, _ = synthetic_track(8)
    body = {"radar": {"range_error_m": 300.0, "azimuth_error_deg": 0.5},
            "plots": [{"t": float(a), "range_m": float(b), "azimuth_deg": float(np.degrees(c))}
                      for a, b, c in zip(plots.t, plots.range_m, plots.azimuth_rad,
                                         strict=True)]}
    serve(body)
    print(f"slim: check passed ({summary['done']} tracks, {summary['plots']} plots, served)")


def serve(body: dict) -> None:
    """``python -m service`` on a free port, with one worker and no compiler: ready within
    120 s, ``/docs`` and its script served, ``body`` reconstructed (200)."""
    import json
    import socket
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "TRAJRECON_HOST": "127.0.0.1", "TRAJRECON_PORT": str(port),
           "TRAJRECON_WORKERS": "1", "CC": "/nonexistent/gcc"}
    url = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "service"], env=env, cwd="/",
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 120
        while True:
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else "exited"
            assert time.monotonic() < end, "the service was not ready within 120 s"
            try:
                if urllib.request.urlopen(url + "/readyz", timeout=2).status == 200:
                    break
            except OSError:
                time.sleep(0.5)
        docs = urllib.request.urlopen(url + "/docs", timeout=10).read().decode()
        script = re.search(r'src="([^"]*swagger-ui-bundle\.js)"', docs)
        assert script and not script.group(1).startswith("http"), docs[:500]
        js = urllib.request.urlopen(url + script.group(1), timeout=10).read()
        assert len(js) > 100_000, len(js)
        req = urllib.request.Request(url + "/v1/reconstructions", json.dumps(body).encode(),
                                     {"Content-Type": "application/json"})
        answer = json.loads(urllib.request.urlopen(req, timeout=60).read())
        assert len(answer["trajectory"]["at_plots"]) == len(body["plots"]), answer
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    log = proc.stderr.read() if proc.stderr else ""
    assert "failed, interpreting it instead" not in log, "the jit cache missed:\n" + log[-2000:]


if __name__ == "__main__":
    if sys.argv[1:2] == ["--check"]:
        check(Path(sys.argv[2]))
    else:
        slim(Path(sys.argv[1]))
