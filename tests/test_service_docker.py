"""docker/Dockerfile without a Docker engine: lint it (hadolint) and replay its steps.

The replay reads the Dockerfile itself (so it cannot drift from it): ENV, WORKDIR, COPY and
the RUN commands run in a fresh virtual environment under a temporary root; then the CMD
serves on a free port and the HEALTHCHECK command must pass. Only user management (``useradd``)
and the system packages (``apt-get``: the C compiler, which this machine has) are
skipped. The fresh venv sees the dependencies already in this venv through a ``.pth`` line
plus uvicorn's console script (the slow part of a real build, downloading wheels, is not what can
break here); the project itself is built and installed by the Dockerfile's own ``pip install``.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import httpx
import yaml
from procs import stop

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
BIN = Path(sys.executable).parent


def instructions(text: str) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` pairs, continuation lines joined, comments dropped."""
    out: list[tuple[str, str]] = []
    logical = ""
    for line in text.splitlines():
        if not logical and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            logical += line.rstrip()[:-1] + " "
            continue
        logical += line
        word, _, rest = logical.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        logical = ""
    return out


def test_dockerfile_passes_hadolint():
    r = subprocess.run([BIN / "hadolint", str(DOCKERFILE)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_dockerfile_has_what_the_image_needs():
    steps = dict(instructions(DOCKERFILE.read_text()))
    assert steps["FROM"].startswith("python:3.11-slim")
    assert steps["USER"] not in ("root", "0")
    assert "/healthz" in steps["HEALTHCHECK"]
    assert json.loads(steps["CMD"])[:2] == ["uvicorn", "service.app:app"]
    runs = [args for word, args in instructions(DOCKERFILE.read_text()) if word == "RUN"]
    assert any("install" in r and " gcc " in r and "libc6-dev" in r for r in runs), \
        "the image needs a C compiler to compile the motion model"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dockerfile_steps_install_and_serve(tmp_path):
    root = tmp_path / "root"  # stands for the image's /
    venv = tmp_path / "venv"  # stands for the base image's Python
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    site = next((venv / "lib").glob("python3*/site-packages"))
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    script = venv / "bin" / "uvicorn"  # the console script pip would install with uvicorn
    script.write_text(f"#!{venv / 'bin' / 'python'}\nimport sys\nfrom uvicorn.main import main\n"
                      "if __name__ == '__main__':\n    sys.exit(main())\n")
    script.chmod(0o755)
    env = {"PATH": f"{venv / 'bin'}{os.pathsep}/usr/bin:/bin", "HOME": str(tmp_path),
           "PIP_FIND_LINKS": os.environ.get("PIP_FIND_LINKS", "")}
    workdir = root

    port = str(_free_port())
    healthcheck: list[str] = []
    cmd: list[str] = []
    for word, args in instructions(DOCKERFILE.read_text()):
        if word == "ENV":
            parts = shlex.split(args)
            env.update(p.split("=", 1) for p in parts)
        elif word == "WORKDIR":
            workdir = root / args.lstrip("/")
            workdir.mkdir(parents=True, exist_ok=True)
        elif word == "COPY":
            *sources, dest = args.split()
            target = workdir / dest
            for src in sources:
                path = ROOT / src
                assert path.exists(), f"COPY {src}: missing in the repository"
                if path.is_dir():
                    shutil.copytree(path, target, ignore=shutil.ignore_patterns("__pycache__"))
                else:
                    target.mkdir(parents=True, exist_ok=True)
                    shutil.copy(path, target / path.name)
        elif word == "RUN":
            for command in args.split("&&"):
                command = command.strip()
                if command.startswith(("useradd ", "apt-get ", "rm -rf /var/lib/apt")):
                    continue  # root and the system's packages: users and the C compiler
                r = subprocess.run(["bash", "-c", command], cwd=workdir, env=env,
                                   capture_output=True, text=True, timeout=300)
                assert r.returncode == 0, f"RUN {command}\n{r.stdout}\n{r.stderr}"
        elif word == "HEALTHCHECK":
            healthcheck = json.loads(args[args.index("CMD") + 3:])
        elif word == "CMD":
            cmd = json.loads(args)
        else:
            assert word in ("FROM", "USER", "EXPOSE"), f"the replay does not know {word}"

    # the installed package, not a source tree, is what runs from the final WORKDIR
    where = subprocess.run(["python", "-c", "import service, solver; print(service.__file__)"],
                           cwd=workdir, env=env, capture_output=True, text=True, check=True)
    assert where.stdout.startswith(str(site)), where.stdout

    cmd = [port if a == "8000" else a for a in cmd]  # the only change: a free port
    cmd = ["127.0.0.1" if a == "0.0.0.0" else a for a in cmd]
    healthcheck = [a.replace(":8000/", f":{port}/") for a in healthcheck]
    proc = subprocess.Popen(cmd, cwd=workdir, env={**env, "TRAJRECON_WORKERS": "1"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        end = time.monotonic() + 60
        while subprocess.run(healthcheck, cwd=workdir, env=env,
                             capture_output=True).returncode != 0:
            assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
            assert time.monotonic() < end, "HEALTHCHECK never passed"
            time.sleep(0.2)
        url = f"http://127.0.0.1:{port}"
        body = json.loads((ROOT / "examples" / "seed_track.json").read_text())
        body["plots"] = body["plots"][:8]
        r = httpx.post(url + "/v1/reconstructions", json=body, timeout=60)
        assert r.status_code == 200, r.text
        assert len(r.json()["trajectory"]["at_plots"]) == 8
    finally:
        stop(proc)


def test_compose_builds_this_dockerfile():
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    (service,) = compose["services"].values()
    build = service["build"]
    context = (ROOT / "docker" / build["context"]).resolve()
    assert context == ROOT and (context / build["dockerfile"]).resolve() == DOCKERFILE
    assert "8000:8000" in service["ports"]
    assert all(k.startswith("TRAJRECON_") for k in service.get("environment", {}))
