"""Helpers for tests that start the service as a real process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A free TCP port on the loopback interface."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_service(env: dict[str, str], timeout: float = 60.0, **popen: object
                  ) -> tuple[subprocess.Popen, str]:
    """``python -m service`` as the README runs it, on a free port, with the environment plus
    ``env``; returns once ``/readyz`` answers 200 (the process and its URL). ``popen``: extra
    ``subprocess.Popen`` arguments (e.g. ``start_new_session``, ``stderr``)."""
    port = free_port()
    full = {**os.environ, "TRAJRECON_PORT": str(port), **env}
    kw: dict = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, **popen}
    proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=full, **kw)
    url = f"http://127.0.0.1:{port}"
    end = time.monotonic() + timeout
    while True:
        if proc.poll() is not None:
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise AssertionError(f"the server exited ({proc.returncode}): {err[-2000:]}")
        if time.monotonic() > end:
            stop(proc)
            raise AssertionError(f"server not ready within {timeout:g} s")
        try:
            if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.1)


def stop(proc: subprocess.Popen) -> None:
    """Terminate ``proc``, killing it if it has not exited within 20 s."""
    proc.terminate()
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
