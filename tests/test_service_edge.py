"""The service's edge on a real server (``python -m service``, raw sockets): framing, parse
errors and slow clients answered with the documented JSON body, bounded metrics and logs, JSON
logs from the first line, compressed answers."""

from __future__ import annotations

import gzip
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from procs import free_port, stop

ROOT = Path(__file__).resolve().parents[1]
SEED_BATCH = json.loads((ROOT / "examples" / "seed_track.json").read_text())


class Server:
    """A running ``python -m service``; ``log`` collects its stderr lines."""

    def __init__(self, port: int, proc: subprocess.Popen):
        self.port, self.proc = port, proc
        self.url = f"http://127.0.0.1:{port}"
        self.log: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.append(line.decode("utf-8", "replace").rstrip("\n"))


@pytest.fixture(scope="module")
def server():
    port = free_port()
    env = {**os.environ, "TRAJRECON_PORT": str(port), "TRAJRECON_WORKERS": "1",
           "TRAJRECON_WARMUP": "false", "TRAJRECON_REQUEST_TIMEOUT_S": "1.5",
           "TRAJRECON_KEEP_ALIVE_S": "1", "TRAJRECON_MAX_CONNECTIONS": "6"}
    proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    srv = Server(port, proc)
    try:
        end = time.monotonic() + 60
        while True:
            assert proc.poll() is None, "\n".join(srv.log)
            assert time.monotonic() < end, "server not ready within 60 s"
            try:
                if httpx.get(srv.url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        yield srv
    finally:
        stop(proc)


def raw(port: int, data: bytes, wait_s: float = 5.0) -> bytes:
    """Send ``data`` on a fresh connection; everything received until the server closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=wait_s) as s:
        s.sendall(data)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out


def parse(answer: bytes) -> tuple[int, dict[str, str], dict]:
    head, _, body = answer.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), headers, json.loads(body)


def test_content_length_with_transfer_encoding_is_400_and_closed(server):
    body = b'{"radar": {}, "plots": []}'
    chunked = f"{len(body):x}\r\n".encode() + body + b"\r\n0\r\n\r\n"
    smuggled = b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n"  # would be a second request
    answer = raw(server.port, b"POST /v1/reconstructions HTTP/1.1\r\nhost: x\r\n"
                 b"content-type: application/json\r\ncontent-length: 4\r\n"
                 b"transfer-encoding: chunked\r\n\r\n" + chunked + smuggled)
    status, headers, err = parse(answer)
    assert status == 400 and headers["connection"] == "close"
    assert "Content-Length and Transfer-Encoding" in err["message"]
    assert answer.count(b"HTTP/1.1 ") == 1, "the connection must close after the 400"


@pytest.mark.parametrize("request_bytes", [
    b"GARBAGE\r\n\r\n",
    b"GET /healthz HTTP/1.1\r\nhost: x\r\ncontent-length: abc\r\n\r\n",
    b"GET /healthz HTTP/1.1\r\nno colon here\r\n\r\n",
])
def test_unparseable_requests_get_the_json_error_body(server, request_bytes):
    status, headers, err = parse(raw(server.port, request_bytes))
    assert status == 400 and headers["content-type"] == "application/json"
    assert err["message"].startswith("invalid HTTP request") and err["detail"]


def test_silent_and_half_sent_requests_are_timed_out(server):
    """A connection that sends nothing, or half a header, is answered 408 and closed after the
    request timeout (1.5 s here), not held for ever."""
    for data in (b"", b"POST /v1/reconstructions HTTP/1.1\r\nhost: x\r\ncontent-le"):
        start = time.monotonic()
        status, _, err = parse(raw(server.port, data, wait_s=10))
        assert status == 408 and "1.5 s" in err["message"]
        assert 1.4 < time.monotonic() - start < 5
    # a body that never ends is cut off the same way
    start = time.monotonic()
    raw(server.port, b"POST /v1/reconstructions HTTP/1.1\r\nhost: x\r\n"
        b"content-type: application/json\r\ncontent-length: 1000\r\n\r\n{", wait_s=10)
    assert time.monotonic() - start < 5


def test_a_slow_but_steady_body_is_not_cut_off(server):
    """The body's limit is on each pause (uploads may be long): 5 pieces 0.5 s apart take
    2.5 s in all, longer than the 1.5-s limit, and the request is answered, not 408."""
    body = json.dumps(dict(SEED_BATCH, plots=SEED_BATCH["plots"][:5], method="sliding"))
    data = body.encode()
    step = -(-len(data) // 5)
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
        s.sendall(b"POST /v1/reconstructions HTTP/1.1\r\nhost: x\r\n"
                  b"content-type: application/json\r\n"
                  + f"content-length: {len(data)}\r\nconnection: close\r\n\r\n".encode())
        for i in range(5):
            time.sleep(0.5)
            s.sendall(data[i * step:(i + 1) * step])
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 200"), answer[:300]


def test_idle_keep_alive_connection_is_closed(server):
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
        start = time.monotonic()
        got = b""
        while chunk := s.recv(65536):
            got += chunk
        assert got.startswith(b"HTTP/1.1 200")
        assert time.monotonic() - start < 4  # keep-alive 1 s here


def test_metrics_stay_bounded_under_junk_methods_and_paths(server):
    with httpx.Client(base_url=server.url) as c:
        for i in range(40):
            c.request(f"JUNK{i}", f"/junk/{i}")
        text = c.get("/metrics").text
    assert "JUNK" not in text and "/junk/" not in text
    series = [ln for ln in text.splitlines()
              if ln.startswith('trajrecon_http_requests_total{method="other"')]
    assert len(series) == 1 and float(series[0].split()[-1]) >= 40


def test_a_request_with_many_errors_logs_a_bounded_summary(server):
    plots = [{"t": "x", "range_m": "y", "azimuth_deg": "z"} for _ in range(3000)]
    before = len(server.log)
    r = httpx.post(server.url + "/v1/reconstructions", timeout=30,
                   json={"radar": {"range_error_m": 1, "azimuth_error_deg": 1}, "plots": plots})
    assert r.status_code == 422
    assert r.json()["message"].endswith("(and 8999 more); the first 100 are listed")
    detail = r.json()["detail"]
    assert len(detail) == 100 and detail[-1]["loc"] == ["plots", 33, "t"]
    assert len(r.content) < 20_000, len(r.content)  # 9000 listed: 0.8 MB
    time.sleep(0.5)
    new = server.log[before:]
    assert any('"invalid request"' in ln and '"errors": 9000' in ln for ln in new), new
    assert all(len(ln) < 10_000 for ln in new), max(map(len, new))


def test_a_long_unknown_key_is_not_echoed_whole(server):
    """A megabyte's key was echoed in the message and the field path: a 2-MB answer."""
    key = "k" * 1_000_000
    r = httpx.post(server.url + "/v1/reconstructions", timeout=30,
                   json={"radar": {"range_error_m": 1, "azimuth_error_deg": 1, key: 1},
                         "plots": SEED_BATCH["plots"][:5]})
    assert r.status_code == 422 and len(r.content) < 1_000, len(r.content)
    short = "k" * 50 + "... (1000000 characters)"
    assert r.json()["message"] == f"radar.{short}: Extra inputs are not permitted"
    assert r.json()["detail"][0]["loc"] == ["radar", short]


def test_answers_are_gzip_compressed_when_accepted(server):
    body = dict(SEED_BATCH, plots=SEED_BATCH["plots"][:40])
    with httpx.Client(base_url=server.url, timeout=60) as c:
        r = c.post("/v1/reconstructions", json=body, headers={"accept-encoding": "gzip"})
        assert r.status_code == 200 and r.headers["content-encoding"] == "gzip"
        assert int(r.headers["content-length"]) < len(r.content) / 2
        assert r.json()["trajectory"]["at_plots"]
        plain = c.post("/v1/reconstructions", json=body, headers={"accept-encoding": "identity"})
        assert "content-encoding" not in plain.headers
        with c.stream("POST", "/v1/reconstructions", json=body,
                      headers={"accept-encoding": "gzip"}) as raw:  # the bytes on the wire
            wire = b"".join(raw.iter_raw())
        assert json.loads(gzip.decompress(wire))["trajectory"]["at_plots"]
        got, want = r.json(), plain.json()  # the same answer (its timings aside)
        assert {k: v for k, v in got.items() if k != "diagnostics"} == {
            k: v for k, v in want.items() if k != "diagnostics"}
        assert got["diagnostics"]["warnings"] == want["diagnostics"]["warnings"]


def test_a_compressed_request_body_is_415_naming_content_encoding(server):
    """Bodies are read as sent: a gzip body got 422 "could not be decoded as UTF-8 JSON" and an
    uncompressed one labelled `br` was read (200; a tester's). Any content coding but identity
    is a 415 naming the header, on both POST routes; `identity` is read as before."""
    body = dict(SEED_BATCH, plots=SEED_BATCH["plots"][:20], omit=["samples"])
    data = json.dumps(body).encode()
    with httpx.Client(base_url=server.url, timeout=60) as c:
        for path in ("/v1/reconstructions", "/v1/jobs"):
            for coding, content in (("gzip", gzip.compress(data)), ("br", data),
                                    ("identity, gzip", gzip.compress(data))):
                r = c.post(path, content=content, headers={
                    "content-type": "application/json", "content-encoding": coding})
                assert r.status_code == 415, (path, coding, r.text)
                assert r.json()["detail"][0]["loc"] == ["headers", "content-encoding"]
                assert r.json()["message"].startswith("Content-Encoding '"), r.json()
        r = c.post("/v1/reconstructions", content=data, headers={
            "content-type": "application/json", "content-encoding": "identity"})
        assert r.status_code == 200, r.text


def test_logs_are_json_from_the_first_line_and_name_the_host(server):
    assert server.log, "no log"
    lines = [json.loads(ln) for ln in server.log]  # every line, the first included
    starting = next(ln for ln in lines if ln["msg"] == "starting")
    assert starting["host"] == "127.0.0.1" and starting["port"] == server.port
    assert any(f"127.0.0.1:{server.port}" in ln["msg"] for ln in lines), lines[:5]


def test_connections_beyond_the_limit_are_refused_at_once(server):
    idle = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(6)]
    try:
        time.sleep(0.2)
        start = time.monotonic()
        status, _, err = parse(raw(server.port, b""))
        assert status == 503 and "6 open connections" in err["message"]
        assert time.monotonic() - start < 1
    finally:
        for s in idle:
            s.close()
    time.sleep(0.2)
    assert httpx.get(server.url + "/healthz").status_code == 200


def test_python_m_service_takes_port_and_workers_options(monkeypatch, capsys):
    """`python -m service --port 8765` listened on 8000 (only TRAJRECON_PORT was read): the
    options set the settings the app reads too; a bad one is a usage error naming it."""
    import service.__main__ as entry
    from service.settings import get_settings

    for name in ("PORT", "WORKERS", "HOST", "DATA_DIR", "DASK_SCHEDULER"):
        # set, then removed: both recorded, so what main() puts there is undone after the
        # test (a delenv of an absent variable records nothing: TRAJRECON_PORT=99999 leaked
        # into the next tests' settings)
        monkeypatch.setenv(f"TRAJRECON_{name}", "")
        monkeypatch.delenv(f"TRAJRECON_{name}")
    served = []
    monkeypatch.setattr(entry, "serve", served.append)
    monkeypatch.setattr(entry, "setup_logging", lambda level: None)
    entry.main(["--port", "8123", "--workers", "1"])
    assert (served[0].port, served[0].workers) == (8123, 1)
    assert get_settings().port == 8123  # what the app, loaded by name, reads
    with pytest.raises(SystemExit) as stop:
        entry.main(["--port", "99999"])
    assert stop.value.code == 2 and "TRAJRECON_PORT: " in capsys.readouterr().err
    get_settings.cache_clear()
