"""docker/Dockerfile without a Docker engine: lint it (hadolint) and replay its steps.

The replay reads the Dockerfile itself (so it cannot drift from it): both stages' ENV,
WORKDIR, COPY and RUN steps run under a temporary root (the image's absolute paths, ``/opt``,
``/src``, ``/home``, are moved under it), with a fresh virtual environment as the base image's
Python; then the CMD serves on a free port (``-e TRAJRECON_PORT=...`` as ``docker run`` would)
and the HEALTHCHECK command must pass. Skipped: user management (``useradd``) and the system
packages (``apt-get``: gcc and binutils, which this machine has and the final stage must not
need: it runs with the real compiler hidden); and the download of the locked dependencies (the
slow part of a real build): the replay copies their installed files from this environment,
after checking that its versions are exactly the lock's, into the replayed virtual
environment, where the Dockerfile's own ``slim.py`` slims them and its ``slim.py --check`` must
then pass on what is left (reconstructions, warm-up, Parquet, PNG figures, the service). The
project itself is built and installed by the Dockerfile's own ``pip install``, and the motion
model is compiled into the cache by its own warm-up step.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
import time
import tomllib
from importlib import metadata
from pathlib import Path

import httpx
import yaml
from packaging.markers import default_environment
from packaging.requirements import Requirement
from procs import free_port, stop

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
LOCK = ROOT / "requirements.lock"
DEV_LOCK = ROOT / "requirements-dev.lock"
BIN = Path(sys.executable).parent


def instructions(text: str) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` pairs, continuation lines joined, comments dropped."""
    out: list[tuple[str, str]] = []
    logical = ""
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        if line.rstrip().endswith("\\"):
            logical += line.rstrip()[:-1] + " "
            continue
        logical += line
        word, _, rest = logical.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        logical = ""
    return out


def stages() -> list[list[tuple[str, str]]]:
    """The instructions of each ``FROM`` stage (the ``FROM`` line first)."""
    out: list[list[tuple[str, str]]] = []
    for word, args in instructions(DOCKERFILE.read_text()):
        if word == "FROM":
            out.append([])
        out[-1].append((word, args))
    return out


def locked(path: Path) -> dict[str, str]:
    """``name -> version`` of the pins in a lock file whose markers hold here."""
    env = default_environment()
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            req = Requirement(line)
            if req.marker is None or req.marker.evaluate(env):
                (spec,) = req.specifier
                pins[req.name.lower().replace("_", "-")] = spec.version
    return pins


def install_locked(site: Path) -> int:
    """The locked distributions' files (no ``.pyc``, as ``pip install --no-compile``), copied
    from this environment into ``site``; bytes copied."""
    here = Path(sysconfig.get_paths()["purelib"])
    copied = 0
    for name in locked(LOCK):
        dist = metadata.distribution(name)
        for file in dist.files or ():
            src = Path(dist.locate_file(file)).resolve()
            if src.suffix == ".pyc" or not src.is_relative_to(here) or not src.is_file():
                continue  # compiled bytecode, and scripts outside site-packages
            out = site / src.relative_to(here)
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, out)
            copied += src.stat().st_size
    return copied


def tree_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def test_dockerfile_passes_hadolint():
    r = subprocess.run([BIN / "hadolint", str(DOCKERFILE)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_dockerfile_has_what_the_image_needs():
    build, final = stages()
    assert build[0][1].startswith("python:3.11-slim AS ")
    assert final[0][1].startswith("python:3.11-slim")
    steps = dict(final)
    assert steps["USER"] not in ("root", "0")
    assert "/readyz" in steps["HEALTHCHECK"] and "--start-interval=1s" in steps["HEALTHCHECK"]
    assert json.loads(steps["CMD"]) == ["python", "-m", "service"]
    assert "TRAJRECON_HOST=0.0.0.0" in steps["ENV"]
    # the locked dependencies are installed before any source is copied (layer caching)
    words = [(w, a) for w, a in build if w in ("COPY", "RUN")]
    lock_install = next(i for i, (w, a) in enumerate(words) if "requirements.lock" in a and
                        w == "RUN")
    first_source = next(i for i, (w, a) in enumerate(words)
                        if w == "COPY" and a.split()[0] in ("solver", "service"))
    assert lock_install < first_source
    # the compiler is in the build stage only
    assert any("gcc" in a for w, a in build if w == "RUN")
    assert not any("gcc" in a or "apt-get" in a for w, a in final if w == "RUN")


def test_dockerignore_keeps_the_context_small():
    ignore = (ROOT / ".dockerignore").read_text().splitlines()
    assert "*" in ignore, "everything is ignored unless listed"
    copied = {a.split()[0].rstrip("/") for w, a in instructions(DOCKERFILE.read_text())
              if w == "COPY" and not a.startswith("--from")}
    allowed = {line[1:].rstrip("/") for line in ignore if line.startswith("!")}
    assert copied <= allowed, copied - allowed


def test_lock_files_cover_pyproject():
    """Every dependency of pyproject.toml (the extras in the dev lock) is pinned in the lock at a
    version its specifier allows; CI and the README install with the dev lock as constraints."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for path, reqs in ((LOCK, project["dependencies"]),
                       (DEV_LOCK, [r for extra in project["optional-dependencies"].values()
                                   for r in extra] + project["dependencies"])):
        pins = locked(path)
        for text in reqs:
            req = Requirement(text)
            name = req.name.lower().replace("_", "-")
            assert name in pins, f"{name} is not in {path.name}: regenerate it (README)"
            assert req.specifier.contains(pins[name], prereleases=True), (name, pins[name])
    assert set(locked(LOCK).items()) <= set(locked(DEV_LOCK).items())
    ci = (ROOT / ".ci" / "run").read_text()
    readme = (ROOT / "README.md").read_text()
    command = next(ln.strip() for ln in ci.splitlines() if "pytest" in ln)
    assert "-c requirements-dev.lock" in command and command in readme


def test_dockerfile_steps_install_and_serve(tmp_path):
    # the replay's stand-in for the lock download: this environment, which must match the lock
    installed = {d.metadata["Name"].lower().replace("_", "-"): d.version
                 for d in metadata.distributions()}
    pins = locked(LOCK)
    assert {k: installed.get(k) for k in pins} == pins, "this venv differs from the lock"

    root = tmp_path / "root"  # stands for the image's /
    base = tmp_path / "base"  # stands for the base image's Python
    installed_bytes = 0
    # the base image's pip is never used: the Dockerfile installs with the venv's own
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(base)], check=True)
    moved = re.compile(r"(?<![\w.$/-])/(opt|src|home|tmp)(?=/|\b)")

    def here(text: str) -> str:
        return moved.sub(lambda m: f"{root}/{m.group(1)}", text)

    env = {"PATH": f"{base / 'bin'}{os.pathsep}/usr/bin:/bin", "HOME": str(tmp_path),
           "PIP_FIND_LINKS": os.environ.get("PIP_FIND_LINKS", "")}
    port = str(free_port())
    healthcheck: list[str] = []
    cmd: list[str] = []
    workdir = root
    for stage in stages():
        for word, args in stage:
            if word == "ENV":
                for part in shlex.split(args):
                    key, value = part.split("=", 1)
                    # the Dockerfile's own paths moved, not those $VARIABLES bring in
                    env[key] = re.sub(r"\$(\w+)", lambda m: env.get(m.group(1), ""), here(value))
            elif word == "WORKDIR":
                workdir = Path(here(args))
                workdir.mkdir(parents=True, exist_ok=True)
            elif word == "COPY":
                if args.startswith("--from="):  # the same root holds both stages' files
                    for path in args.split()[1:]:
                        assert Path(here(path)).exists(), path
                    continue
                *sources, dest = args.split()
                target = Path(here(dest)) if dest.startswith("/") else workdir / dest
                for src in sources:
                    path = ROOT / src
                    assert path.exists(), f"COPY {src}: missing in the repository"
                    if path.is_dir():
                        shutil.copytree(path, target,
                                        ignore=shutil.ignore_patterns("__pycache__"))
                    elif dest.endswith("/"):
                        target.mkdir(parents=True, exist_ok=True)
                        shutil.copy(path, target / path.name)
                    else:
                        target.parent.mkdir(parents=True, exist_ok=True)
                        shutil.copy(path, target)
            elif word == "RUN":
                for command in args.split("&&"):
                    command = command.strip()
                    if command.startswith(("useradd ", "apt-get ", "rm -rf /var/lib/apt")):
                        continue  # root and the system's packages: users and gcc
                    if "--requirement requirements.lock" in command:
                        venv = Path(env["VIRTUAL_ENV"])
                        site = next((venv / "lib").glob("python3*/site-packages"))
                        installed_bytes = install_locked(site)
                        continue
                    r = subprocess.run(["bash", "-c", here(command)], cwd=workdir, env=env,
                                       capture_output=True, text=True, timeout=600)
                    assert r.returncode == 0, f"RUN {command}\n{r.stdout}\n{r.stderr}"
            elif word == "HEALTHCHECK":
                healthcheck = json.loads(args[args.index("CMD") + 3:])
            elif word == "CMD":
                cmd = json.loads(args)
            else:
                assert word in ("FROM", "USER", "EXPOSE"), f"the replay does not know {word}"

    # slim.py slimmed the locked set (its --check passed on what is left, or the RUN failed)
    site = next((Path(env["VIRTUAL_ENV"]) / "lib").glob("python3*/site-packages"))
    slimmed = tree_size(site)
    assert slimmed < 0.5 * installed_bytes, (slimmed, installed_bytes)
    assert slimmed < 380e6, f"the venv is {slimmed / 1e6:.0f} MB: the image's budget is 500 MB"
    assert (site / "casadi" / "libcasadi_nlpsol_ipopt.so").exists()
    assert not list(site.glob("casadi/libcasadi_nlpsol_uno.so*"))
    assert not (site / "scipy" / "stats").exists() and not (site / "pip").exists()
    assert (site / "casadi" / "libcasadi.so.3.7").is_symlink()  # a duplicate, linked
    # .pyc only for what the check imported: the ASTERIX tables yes, matplotlib's PDF no
    assert list(site.glob("asterix/__pycache__/generated.*.pyc"))
    assert not list(site.glob("matplotlib/backends/__pycache__/backend_pdf.*.pyc"))

    # the installed package, not a source tree, is what runs from the final WORKDIR
    where = subprocess.run(["python", "-c", "import service, solver; print(service.__file__)"],
                           cwd=workdir, env=env, capture_output=True, text=True, check=True)
    assert where.stdout.startswith(env["VIRTUAL_ENV"]), where.stdout
    cache = Path(env["TRAJRECON_JIT_CACHE"])
    assert list(cache.glob("*.so")), "nothing compiled at build"
    # the build stage fills the cache as root, the final stage (USER 10001) must read it
    unreadable = [e.name for e in cache.iterdir() if not e.stat().st_mode & 0o004]
    assert not unreadable, f"not readable by other users: {unreadable[:3]}"

    # docker run -e TRAJRECON_PORT=<port> -e TRAJRECON_HOST=127.0.0.1, and no compiler
    run_env = {**env, "TRAJRECON_WORKERS": "1", "TRAJRECON_PORT": port,
               "TRAJRECON_HOST": "127.0.0.1", "CC": "/nonexistent/gcc"}
    proc = subprocess.Popen(cmd, cwd=workdir, env=run_env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 90
        while subprocess.run(healthcheck, cwd=workdir, env=run_env,
                             capture_output=True).returncode != 0:
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            assert time.monotonic() < end, "HEALTHCHECK never passed"
            time.sleep(0.2)
        url = f"http://127.0.0.1:{port}"
        body = json.loads((ROOT / "examples" / "seed_track.json").read_text())
        body["plots"] = body["plots"][:8]
        r = httpx.post(url + "/v1/reconstructions", json=body, timeout=60)
        assert r.status_code == 200, r.text
        assert len(r.json()["trajectory"]["at_plots"]) == 8
        assert httpx.get(url + "/docs").status_code == 200
    finally:
        stop(proc)
    log = [json.loads(line) for line in proc.stderr.read().splitlines()]  # JSON from line 1
    starting = next(line for line in log if line["msg"] == "starting")
    assert (starting["host"], starting["port"]) == ("127.0.0.1", int(port))
    # no compiler: the objects compiled at build time, through the caching front
    assert starting["c_compiler"] == "none"
    front = f" {env['TRAJRECON_JIT_CACHE']} {platform.machine()} -"
    assert starting["jit"].endswith(front), starting["jit"]
    failed = [line for line in log if "failed, interpreting it instead" in line["msg"]]
    assert not failed, "the build-time cache missed: " + str(failed[:1])


def test_compose_builds_this_dockerfile():
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    (service,) = compose["services"].values()
    build = service["build"]
    context = (ROOT / "docker" / build["context"]).resolve()
    assert context == ROOT and (context / build["dockerfile"]).resolve() == DOCKERFILE
    assert "8000:8000" in service["ports"]
    assert all(k.startswith("TRAJRECON_") for k in service.get("environment", {}))
