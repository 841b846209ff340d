"""Admission of large job answers (:class:`service.admission.BuildSlots`): a client that
leaves while its answer waits for a build slot gives its place up, and one gone by the time
a slot is free has nothing built (a reviewer's 30 abandoned requests had their 56-MB answers
built one after another: a small answer behind them took 134.6 s)."""

from __future__ import annotations

import asyncio
import time

import pytest
from fastapi.testclient import TestClient

from service.admission import DISCONNECT_POLL_S, BuildSlots, Gone
from service.app import create_app
from service.settings import Settings


def test_a_client_gone_while_waiting_gives_its_place_up_and_nothing_is_built():
    built: list[str] = []

    def build(name: str) -> str:
        built.append(name)
        return name

    async def scenario() -> None:
        slots = BuildSlots(1, 8)
        await slots.acquire()  # an answer being built
        left = False

        async def gone() -> bool:
            return left

        waiting = asyncio.ensure_future(slots.build(build, "abandoned", gone=gone))
        stays = asyncio.ensure_future(slots.build(build, "stays"))
        await asyncio.sleep(0.05)
        assert slots.waiting == 2
        left = True
        start = time.monotonic()
        with pytest.raises(Gone):
            await waiting
        assert time.monotonic() - start < 2 * DISCONNECT_POLL_S + 0.5
        assert slots.waiting == 1  # the other one still waits
        slots.release()
        assert await stays == "stays"
        assert (slots.building, slots.waiting) == (0, 0)
        # gone by the time its slot is free: nothing built, the slot given back
        with pytest.raises(Gone):
            await slots.build(build, "late", gone=gone)
        assert (slots.building, slots.waiting) == (0, 0)

    asyncio.run(scenario())
    assert built == ["stays"]


def test_a_job_answer_whose_client_left_is_499_and_frees_its_place(tmp_path):
    """Through the application: both build slots taken, a GET of a track list whose client
    has gone is dropped (499) within a poll or two, and no place stays taken."""
    app = create_app(Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                              data_dir=tmp_path, jobs_answer_builds=1))
    sent: list[dict] = []

    async def receive() -> dict:
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": "GET", "scheme": "http", "path": "/v1/jobs/nope/tracks",
             "raw_path": b"/v1/jobs/nope/tracks", "query_string": b"", "root_path": "",
             "client": ("127.0.0.1", 5000), "server": ("127.0.0.1", 8000), "state": {},
             "headers": [(b"host", b"testserver")]}

    async def scenario() -> None:
        slots: BuildSlots = app.state.answer_slots
        await slots.acquire()
        start = time.monotonic()
        await asyncio.wait_for(app(scope, receive, send), 10)  # it waited for the slot
        assert time.monotonic() - start < 2 * DISCONNECT_POLL_S + 1.0
        assert (slots.building, slots.waiting) == (1, 0)
        slots.release()

    with TestClient(app):  # the job runner started (else 503); the request on a loop of its own
        asyncio.run(scenario())
    starts = [m for m in sent if m["type"] == "http.response.start"]
    assert [m["status"] for m in starts] == [499], sent
