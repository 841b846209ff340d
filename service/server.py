"""The HTTP server: uvicorn with an h11 protocol that keeps the service's edge contract.

uvicorn answers a request it cannot parse itself, in plain text, and times a connection out only
while it is idle *between* requests: a client that connects and sends nothing, or half a
header, holds the connection for ever. :class:`Protocol` answers those parse errors with the
documented JSON error body, refuses connections beyond ``max_connections`` (503, JSON), and
bounds how long a request may take to arrive: its headers must
arrive whole within ``request_timeout_s`` of the connection (or the previous answer), and its
body may pause no longer than that between two reads; past either, 408 (JSON) and the
connection is closed.
"""

from __future__ import annotations

import asyncio
import json
import sys
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from .logs import LOGGER
from .settings import Settings


def error_bytes(status: int, reason: str, message: str, kind: str) -> bytes:
    """A complete ``Connection: close`` HTTP/1.1 answer with an ``ErrorResponse`` body."""
    body = json.dumps({"message": message,
                       "detail": [{"loc": [], "msg": message, "type": kind}]}).encode()
    head = (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\n"
            f"content-length: {len(body)}\r\nconnection: close\r\n\r\n")
    return head.encode("ascii") + body


class Protocol(H11Protocol):
    """h11 protocol with JSON 400s and the arrival limits of the module docstring
    (``request_timeout_s``, set by :func:`config`)."""

    request_timeout_s: float = 30.0
    max_connections: int = 1000

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self._arrival: asyncio.TimerHandle | None = None
        super().connection_made(transport)
        if len(self.connections) > self.max_connections:
            # each open connection holds memory and a file descriptor: refuse at once
            transport.write(error_bytes(
                503, "Service Unavailable", f"the server has {self.max_connections} open "
                "connections, its limit; retry later", "too_many_connections"))
            transport.close()
            return
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        state = self.conn.their_state
        if state in (h11.DONE, h11.MUST_CLOSE, h11.CLOSED, h11.ERROR):
            self._disarm()  # the request has arrived whole: the app takes over
        elif state is h11.SEND_BODY and self._arrival is not None:
            self._arm()  # a body may be long (uploads): the limit is on each pause in it

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm()  # the next request on this connection gets its own deadline

    def _arm(self) -> None:
        self._disarm()
        self._arrival = self.loop.call_later(self.request_timeout_s, self._too_slow)

    def _disarm(self) -> None:
        if getattr(self, "_arrival", None) is not None:
            self._arrival.cancel()  # type: ignore[union-attr]
            self._arrival = None

    def _too_slow(self) -> None:
        """The request did not arrive whole in time: 408 if nothing was answered yet, close."""
        self._arrival = None
        if self.transport.is_closing():
            return
        if self.cycle is None or self.cycle.response_complete or not self.cycle.response_started:
            LOGGER.info("request timeout", extra={"fields": {
                "client": (self.client or ("", 0))[0], "after_s": self.request_timeout_s}})
            self.transport.write(error_bytes(
                408, "Request Timeout", f"the request did not arrive within "
                f"{self.request_timeout_s:g} s", "request_timeout"))
        if self.cycle is not None and not self.cycle.response_complete:
            self.cycle.disconnected = True
            self.cycle.message_event.set()  # the app's receive() sees a disconnect
        self.transport.close()

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to an unparseable request, as an ``ErrorResponse``; the parser's
        own reason (``h11``'s exception, being handled) is in the message."""
        exc = sys.exc_info()[1]
        reason = str(exc) if isinstance(exc, h11.RemoteProtocolError) and str(exc) else msg
        self.transport.write(error_bytes(400, "Bad Request",
                                         f"invalid HTTP request: {reason}", "http_invalid"))
        self.transport.close()


def config(settings: Settings, app: Any = "service.app:app") -> uvicorn.Config:
    """uvicorn's configuration for ``settings``: this module's protocol, the service's
    timeouts, JSON logs (``log_config=None`` keeps :func:`service.logs.setup_logging`'s)."""
    protocol = type("Protocol", (Protocol,), {"request_timeout_s": settings.request_timeout_s,
                                              "max_connections": settings.max_connections})
    return uvicorn.Config(
        app, host=settings.host, port=settings.port, http=protocol,
        log_level=settings.log_level.lower(), log_config=None, access_log=False,
        proxy_headers=True, timeout_keep_alive=settings.keep_alive_s,
        timeout_graceful_shutdown=settings.shutdown_timeout_s,
        h11_max_incomplete_event_size=16 * 1024)


def serve(settings: Settings) -> None:
    """Run the service until SIGINT/SIGTERM."""
    uvicorn.Server(config(settings)).run()
