"""The FastAPI application: ``service.app:app`` (contract: spec/api.md, version 1)."""

from __future__ import annotations

import asyncio
import gc
import json
import re
import sqlite3
import time
import uuid
from collections.abc import AsyncIterator, Coroutine
from contextlib import asynccontextmanager
from typing import Any

import swagger_ui_bundle
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.exceptions import HTTPException
from starlette.middleware.gzip import GZipMiddleware
from starlette.requests import ClientDisconnect
from starlette.routing import BaseRoute, Match
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from solver import compiled
from solver.inputs import InputError, format_loc
from solver.json_keys import TWICE, duplicate_key

from . import __version__
from .admission import DISCONNECT_POLL_S
from .convert import client_loc, to_job
from .logs import LOGGER, setup_logging
from .metrics import Metrics
from .models import (
    ErrorResponse,
    Health,
    ReconstructionRequest,
    ReconstructionResponse,
    shortened,
)
from .pool import Busy, SolverPool
from .routes_jobs import HEAD_ONLY, JOBS_PATH, JobsBodyLimit, install_jobs
from .settings import Settings, get_settings
from .workers import Outcome, SolveError

DESCRIPTION = """\
Reconstructs one aircraft's trajectory from a batch of radar plots (time, slant range, azimuth)
by one bounded piecewise-constant-control CasADi NLP over the whole track (default) or by the
seed's sliding constant-control windows (each window a bounded CasADi NLP), and runs recursive
filters beside it.

**Conventions.** SI units; the unit is in every field name. Horizontal plane centred on the
radar: `x` north, `z` east (m). Azimuth and heading in degrees, clockwise from north.
Velocities in m/s, accelerations in m/s^2, times in s (any origin, strictly increasing).

**Errors.** Every error answer is an `ErrorResponse`: `message` names the field and, for plots,
the index (`plots[17].t is not after plots[16].t (38.2 <= 40.0)`); `detail` lists every problem.
422: malformed or physically impossible input (NaN and Infinity included; JSON syntax errors
with line and column), or a solve over the service's time or memory limit; 413: body over the
size limit; 400: a request HTTP cannot parse, or with both `Content-Length` and
`Transfer-Encoding` (the connection is closed); 415: a body not sent as JSON, or with a
`Content-Encoding` other than `identity` (bodies are read uncompressed); 408: a request that
did not arrive in time; 503: all solvers busy and the queue full (see `Retry-After`).
"""

_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorResponse, "description": "Unparseable HTTP, or both Content-Length and "
          "Transfer-Encoding (the connection is closed)."},
    408: {"model": ErrorResponse, "description": "The request did not arrive in time (the "
          "connection is closed)."},
    413: {"model": ErrorResponse, "description": "Request body over the size limit."},
    415: {"model": ErrorResponse, "description": "The body is not sent as JSON (its "
          "Content-Type is not application/json), or with a Content-Encoding other than "
          "identity."},
    422: {"model": ErrorResponse, "description": "Invalid input; the message names the field "
          "and plot index."},
    500: {"model": ErrorResponse, "description": "Internal error (a bug; never bad input)."},
    503: {"model": ErrorResponse, "description": "Solvers busy and queue full; retry after "
          "`Retry-After` seconds."},
}


DOCS_ASSETS = "/docs/assets"


async def _unless_gone(request: Request, work: Coroutine[Any, Any, Outcome]) -> Outcome | None:
    """``await work``, cancelled (None) when the client disconnects first: a tester's six
    requests abandoned by their clients after 2 s held the queue, and a quick request behind
    them took 28 s instead of 0.35 s. A solve already running finishes in its worker, which
    then takes the next (:meth:`SolverPool._reclaim`); a queued one leaves the queue."""
    task = asyncio.ensure_future(work)
    while True:
        done, _ = await asyncio.wait({task}, timeout=DISCONNECT_POLL_S)
        if done:
            return task.result()
        if await request.is_disconnected():
            task.cancel()
            LOGGER.info("client went away; its reconstruction was dropped")
            return None


async def _undecodable(request: Request) -> str:
    """Why FastAPI could not decode a body (it says only 'There was an error parsing the
    body'): not UTF-8 text, nested too deep for Python's parser, or an integer too long."""
    try:
        json.loads(await request.body())
    except UnicodeDecodeError:
        return "could not be decoded as UTF-8 JSON"
    except RecursionError:
        return "is nested too deeply for the JSON parser (at most several hundred levels)"
    except ValueError as e:  # e.g. 'Exceeds the limit (4300 digits) for integer string ...'
        return f"could not be decoded as JSON: {str(e).split(';')[0]}"
    except Exception as e:
        return f"could not be decoded as JSON ({type(e).__name__})"
    return "could not be decoded as JSON"


def _error(status: int, message: str, detail: list[dict[str, Any]] | None = None,
           headers: dict[str, str] | None = None) -> JSONResponse:
    body = ErrorResponse.model_validate({"message": message, "detail": detail or []})
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


def _clean_loc(loc: tuple[Any, ...]) -> list[str | int]:
    """FastAPI's ``("body", "plots", 3, "t")`` -> ``["plots", 3, "t"]``; a sensor's kind,
    which pydantic puts in the path of a tagged union's member (``sensors[1].radar.
    range_error_m``), left out: the field is ``sensors[1].range_error_m``. A name longer
    than :data:`service.models.MAX_ECHO_CHARS` is shortened."""
    parts = [p if isinstance(p, int) else shortened(str(p)) for p in loc]
    parts = parts[1:] if parts[:1] == ["body"] and len(parts) > 1 else parts
    return [p for k, p in enumerate(parts)
            if not (k >= 2 and parts[k - 2] == "sensors" and isinstance(parts[k - 1], int)
                    and p in ("radar", "position"))]


def _line_column(doc: Any, pos: int) -> tuple[int, int]:
    """1-based line and column of character ``pos`` of the JSON text ``doc``."""
    text = doc.decode("utf-8", "replace") if isinstance(doc, bytes) else str(doc or "")
    before = text[:pos]
    return before.count("\n") + 1, pos - (before.rfind("\n") + 1) + 1


def _is_json(content_type: str) -> bool:
    """Whether FastAPI parses a body of this media type as JSON (``application/json``,
    ``application/*+json``)."""
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/")
                                            and media.endswith("+json"))


MAX_ERRORS_LISTED = 100
"""An invalid body's errors listed in the answer's ``detail`` (its message counts them all).
Listing every one, a 1.9-MB body of 40,000 plots with three bad fields each was answered 11 MB
of ``detail`` after 7 s in the event loop (pydantic's validation and error list: 0.45 s)."""

def _validation_items(exc: RequestValidationError) -> tuple[list[dict[str, Any]], int]:
    """The first :data:`MAX_ERRORS_LISTED` errors in the documented shape, and how many there
    are; a JSON syntax error says where it is as line and column (FastAPI gives a bare
    character offset as the field path)."""
    items = []
    errors = exc.errors()
    for e in errors[:MAX_ERRORS_LISTED]:
        if e.get("type") == "json_invalid":
            body = getattr(exc, "body", b"") or b""
            what = str((e.get("ctx") or {}).get("error", "invalid JSON"))
            if not (body.strip() if isinstance(body, bytes | str) else body):
                items.append({"loc": ["body"], "type": "missing",
                              "msg": "is empty: the request is a JSON object in the body"})
            elif re.search(r" at line \d+ column \d+$", what):  # pydantic's (a jobs body)
                items.append({"loc": ["body"], "type": "json_invalid",
                              "msg": f"is not valid JSON: {what}"})
            else:  # FastAPI's: a character offset as the field path
                pos = next((p for p in e.get("loc", ())[1:] if isinstance(p, int)), 0)
                line, col = _line_column(body, pos)
                items.append({"loc": ["body"], "type": "json_invalid",
                              "msg": f"is not valid JSON: {what} at line {line} column {col} "
                              f"(char {pos})"})
            continue
        items.append({"loc": _clean_loc(tuple(e.get("loc", ()))), "msg": str(e.get("msg", "")),
                      "type": str(e.get("type", "value_error"))})
    return items, len(errors)


# ------------------------------------------------------------------------------ middleware


class BodyLimit:
    """Refuse bodies over ``max_bytes`` with a JSON 413: at once from ``Content-Length``, else
    while reading a chunked body. (FastAPI's own ``max_body_size`` answers plain text when
    ``Content-Length`` is over the limit; every error here is an ``ErrorResponse``.)"""

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.max_bytes:
            await _too_large(self.max_bytes)(scope, receive, send)
            return
        received = 0

        async def limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise HTTPException(413)
            return message

        await self.app(scope, limited, send)


def _too_large(max_bytes: int) -> JSONResponse:
    return _error(413, f"request body is larger than the limit of {max_bytes} bytes")


class Framing:
    """Answer 400 to a request that carries both ``Content-Length`` and ``Transfer-Encoding``.

    The HTTP parser (h11) lets ``Transfer-Encoding`` win; a proxy in front may pick
    ``Content-Length`` instead, and the two then disagree on where the request ends (request
    smuggling; RFC 9112 section 6.3 allows a server to reject such a message). The answer closes
    the connection, so nothing after the ambiguous body is read as a request."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            names = {name for name, _ in scope["headers"]}
            if b"content-length" in names and b"transfer-encoding" in names:
                response = _error(400, "the request has both Content-Length and "
                                  "Transfer-Encoding; send one of them",
                                  [{"loc": ["headers"], "type": "ambiguous_framing",
                                    "msg": "both Content-Length and Transfer-Encoding"}],
                                  headers={"connection": "close"})
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


class ContentCoding:
    """Answer 415 naming ``Content-Encoding`` to a request whose body has a content coding
    other than ``identity``: bodies are read as sent, so a gzip body was refused as "could not
    be decoded as UTF-8 JSON" and an uncompressed one labelled ``br`` was read as if
    unlabelled (a tester's); RFC 9110 section 8.4.1 asks for the 415. Nothing is decoded, so
    the cost stays the body limit's."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            codings = [c.strip().lower() for name, value in scope["headers"]
                       if name == b"content-encoding"
                       for c in value.decode("latin-1").split(",")]
            other = [c for c in codings if c not in ("", "identity")]
            if other:
                msg = (f"Content-Encoding {', '.join(other)[:80]!r} is not supported: send the "
                       "body uncompressed (no Content-Encoding, or identity)")
                response = _error(415, msg,
                                  [{"loc": ["headers", "content-encoding"], "msg": msg,
                                    "type": "unsupported_content_encoding"}])
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


class HeadAsGet:
    """Answer ``HEAD`` as ``GET`` without its body where no route takes ``HEAD`` itself
    (FastAPI routes a ``GET`` route for ``GET`` only: figures, results and a job's status
    answered ``HEAD`` with 405; RFC 9110 9.3.2). Status and headers are the ``GET``'s,
    ``Content-Length`` included; the body is dropped here (and by the server)."""

    def __init__(self, app: ASGIApp, routes: list[BaseRoute]):
        self.app = app
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD" or any(
                r.matches(scope)[0] is Match.FULL for r in self.routes):
            await self.app(scope, receive, send)
            return

        async def headers_only(message: Message) -> None:
            if message["type"] == "http.response.body":
                if message.get("more_body", False):
                    return
                message = {"type": "http.response.body", "body": b"", "more_body": False}
            await send(message)

        inner = {**scope, "method": "GET", HEAD_ONLY: True}  # a copy: the server's is HEAD
        try:
            await self.app(inner, receive, headers_only)
        finally:
            if "route" in inner:  # for Observe's route label
                scope.setdefault("route", inner["route"])


# the method label takes these values only: any other token is counted as "other", so junk
# methods cannot create new Prometheus series
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class Observe:
    """Time every request; count it in the metrics; log one JSON line; echo X-Request-ID.

    Metric labels are bounded: the route is the matched route's template (``<unmatched>``
    otherwise) and the method one of :data:`KNOWN_METHODS` or ``other``."""

    def __init__(self, app: ASGIApp, metrics: Metrics, access_log: bool,
                 routes: list[BaseRoute] | None = None):
        self.app = app
        self.metrics = metrics
        self.access_log = access_log
        self.routes = routes if routes is not None else []

    def route_label(self, scope: Scope, original: Scope) -> str:
        """The matched route's template. FastAPI's routes leave themselves in the scope; for the
        others (``/openapi.json``, the docs' assets mount) the app's routes are matched again
        against the ``original`` scope (routing rewrites ``root_path`` in place)."""
        route = scope.get("route")
        if route is None:
            route = next((r for r in self.routes if r.matches(original)[0] is Match.FULL), None)
        return getattr(route, "path", None) or "<unmatched>"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        original = dict(scope)
        headers = dict(scope["headers"])
        rid = headers.get(b"x-request-id", b"").decode("latin-1")[:64] or uuid.uuid4().hex[:16]
        status = 500

        async def send_observed(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"],
                                      (b"x-request-id", rid.encode("latin-1"))]
            await send(message)

        try:
            await self.app(scope, receive, send_observed)
        finally:
            elapsed = time.perf_counter() - start
            path = self.route_label(scope, original) if status != 404 else "<unmatched>"
            method = scope["method"] if scope["method"] in KNOWN_METHODS else "other"
            self.metrics.requests.labels(method, path, str(status)).inc()
            self.metrics.latency.labels(method, path).observe(elapsed)
            if self.access_log:
                LOGGER.info("request", extra={"fields": {
                    "request_id": rid, "method": scope["method"][:16],
                    "path": scope["path"][:256], "route": path,
                    "status": status, "duration_ms": round(elapsed * 1e3, 2),
                    "client": (scope.get("client") or ("", 0))[0],
                    "content_length": headers.get(b"content-length", b"").decode("latin-1")}})


# ------------------------------------------------------------------------------------- app


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the application for ``settings`` (default: from the environment)."""
    settings = settings or get_settings()
    metrics = Metrics()
    pool = SolverPool(settings, metrics)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        setup_logging(settings.log_level)
        LOGGER.info("starting", extra={"fields": {
            **settings.model_dump(),
            "c_compiler": compiled.compiler() or "none",
            "jit": compiled.jit_command() or "none: the motion model is interpreted"}})
        pool.start()
        jobs.start()
        # the startup's objects (modules, schemas) out of every later full collection: the
        # collections a large job answer's rows set off held the event loop (20 concurrent
        # 19.6-MB track answers: 52.6 s and /healthz up to 2.2 s; frozen: 33.9 s, 1.2 s).
        # Once a process: a test process starts many apps
        if not gc.get_freeze_count():
            gc.collect()
            gc.freeze()
        yield
        await jobs.aclose()
        await pool.close()

    app = FastAPI(
        title="Radar trajectory reconstruction",
        version=__version__,
        summary="Best-estimate aircraft trajectories from recorded radar plots.",
        description=DESCRIPTION,
        lifespan=lifespan,
        generate_unique_id_function=lambda route: route.name,  # operationId = function name
        openapi_tags=[
            {"name": "reconstruction", "description": "Trajectory reconstruction."},
            {"name": "operations", "description": "Health, readiness and metrics."},
        ],
        docs_url=None,  # FastAPI's pages load their scripts from a CDN: see /docs below
        redoc_url=None,
    )
    # Swagger UI from the swagger-ui-bundle package, so /docs works on an offline network
    app.mount(DOCS_ASSETS, StaticFiles(directory=swagger_ui_bundle.swagger_ui_path),
              name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url="/openapi.json", title="Radar trajectory reconstruction - API",
            swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_ASSETS}/favicon-32x32.png")
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.pool = pool
    jobs = install_jobs(app, settings)  # /v1/jobs (service.routes_jobs)
    # outermost last: Observe sees every answer (framing and size refusals included); gzip
    # at level 1: the 2.56-MB sample answer becomes 1.04 MB in 25 ms (level 6: 0.97 MB in
    # 120 ms); answers over 128 KiB are compressed in a thread, off the event loop
    app.add_middleware(JobsBodyLimit, limit=BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(GZipMiddleware, minimum_size=1024, compresslevel=1)
    app.add_middleware(HeadAsGet, routes=app.router.routes)
    app.add_middleware(ContentCoding)
    app.add_middleware(Framing)
    app.add_middleware(Observe, metrics=metrics, access_log=settings.access_log,
                       routes=app.router.routes)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        items, total = _validation_items(exc)
        first = items[0] if items else {"loc": [], "msg": "invalid request"}
        where = format_loc(tuple(first["loc"])) or "body"
        more = f" (and {total - 1} more)" if total > 1 else ""
        if total > len(items):
            more += f"; the first {len(items)} are listed"
        message = f"{where}: {first['msg']}{more}"
        kind = request.headers.get("content-type", "")
        if first["loc"] == ["body"] and first.get("type") == "model_attributes_type" and \
                not _is_json(kind):  # FastAPI reads a body as JSON only when it says it is
            said = f"its Content-Type is {kind!r}" if kind else "it has no Content-Type"
            msg = (f"the body is not read as JSON: {said}; send 'Content-Type: "
                   "application/json' (curl: -H 'content-type: application/json')")
            return _error(415, msg, [{"loc": ["headers", "content-type"], "msg": msg,
                                      "type": "unsupported_media_type"}])
        if first["loc"] == ["body"] and first.get("type") == "missing":
            msg = "is empty: the request is a JSON object in the body"
            message, items[0] = f"body: {msg}", {**first, "msg": msg}
        # a summary, never the list: one body can carry 10^5 errors
        LOGGER.info("invalid request", extra={"fields": {
            "errors": total, "first": message[:300]}})
        return _error(422, message, items)

    @app.exception_handler(InputError)
    async def invalid_input(request: Request, exc: InputError) -> JSONResponse:
        """Every input error, early (``to_job``) or late (from a worker), is renamed to the
        request's field names here, in one place (``azimuth_rad`` -> ``azimuth_deg``)."""
        loc = client_loc(tuple(exc.loc))
        msg = f"{format_loc(loc)} {exc.message}"
        return _error(422, msg, [{"loc": list(loc), "msg": msg, "type": "value_error"}])

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, exc: HTTPException) -> JSONResponse:
        if exc.status_code == 413:
            return _too_large(settings.max_body_bytes)
        if exc.status_code == 400:  # FastAPI: a body json.loads refused (not its JSON errors)
            why = await _undecodable(request)
            return _error(422, f"body: {why}",
                          [{"loc": ["body"], "msg": why, "type": "json_invalid"}])
        return _error(exc.status_code, str(exc.detail), headers=exc.headers)

    @app.exception_handler(sqlite3.OperationalError)
    async def store_error(request: Request, exc: sqlite3.OperationalError) -> JSONResponse:
        LOGGER.error("job store error", exc_info=exc)
        return _error(503, f"the job store cannot be written now ({exc}): free room on its "
                      "disk or retry later", headers={"Retry-After": str(settings.retry_after_s)})

    @app.exception_handler(ClientDisconnect)
    async def client_gone(request: Request, exc: ClientDisconnect) -> Response:
        """A client that closed its connection mid-upload: nobody reads an answer (499, as
        the single-track route; it was logged as an unhandled error and counted a 500)."""
        LOGGER.info("client disconnected", extra={"fields": {"path": request.url.path}})
        return Response(status_code=499)

    @app.exception_handler(FileNotFoundError)
    async def file_gone(request: Request, exc: FileNotFoundError) -> JSONResponse:
        """A job's file gone while it was read because the job was deleted meanwhile (a DELETE
        racing reads gave 500s): 404; any other missing file is an internal error."""
        job_id = request.path_params.get("job_id")
        jobs = getattr(request.app.state, "jobs", None)
        try:
            gone = job_id is not None and jobs is not None and jobs.get(job_id) is None
        except Exception:  # the store closed (stopping): not known to be gone
            gone = False
        if request.url.path.startswith(JOBS_PATH + "/") and gone:
            return _error(404, f"job {shortened(job_id)} not found: it was deleted while this "
                          "was read")
        LOGGER.error("unhandled error", exc_info=exc)
        return _error(500, f"internal error: {type(exc).__name__}")

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception) -> JSONResponse:
        LOGGER.error("unhandled error", exc_info=exc)
        return _error(500, f"internal error: {type(exc).__name__}")

    @app.post("/v1/reconstructions", response_model=ReconstructionResponse, responses=_ERRORS,
              tags=["reconstruction"], summary="Reconstruct a trajectory from radar plots")
    async def create_reconstruction(body: ReconstructionRequest, request: Request) -> Response:
        """Reconstruct one aircraft's trajectory from its plots, and run the requested filters.

        The solve runs in a worker process; while all workers are busy the request waits in a
        bounded queue (503 with `Retry-After` when that is full too). A request whose client
        has gone leaves the queue.
        """
        twice = await run_in_threadpool(duplicate_key, await request.body())
        if twice is not None:
            raise InputError(twice, TWICE)
        job = to_job(body, settings.nlp_solver, settings.max_plots, settings.max_samples,
                     settings.max_nodes)
        try:
            outcome = await _unless_gone(request, pool.run(job))
            if outcome is None:
                return Response(status_code=499)  # nobody reads it (nginx's 'client closed')
        except Busy as e:
            return _error(503, str(e), headers={"Retry-After": str(settings.retry_after_s)})
        except SolveError as e:
            metrics.solves.labels(job.config.method, "error").inc()
            LOGGER.error("solve failed", extra={"fields": {"error": str(e)[:4000]}})
            return _error(500, "the reconstruction failed: " + str(e).splitlines()[0][:300])
        if outcome.body is None:
            metrics.solves.labels(job.config.method, "input_error").inc()
            raise InputError(outcome.error_loc, outcome.error_message)
        metrics.solves.labels(job.config.method, "ok").inc()
        metrics.solver_failures.inc(outcome.solver_failures)
        return Response(outcome.body, media_type="application/json")

    @app.get("/healthz", response_model=Health, tags=["operations"], summary="Liveness")
    async def healthz() -> Health:
        """The process is alive and its event loop answers (also while solving)."""
        return Health(status="ok")

    @app.get("/readyz", response_model=Health, tags=["operations"], summary="Readiness",
             responses={503: {"model": Health, "description": "Not ready (yet)."}})
    async def readyz() -> Response:
        """Ready once every worker has built and warmed the CasADi solvers, and while one of
        them is alive (dead idle workers are replaced here)."""
        health = Health(status=pool.state, detail=pool.detail)  # type: ignore[arg-type]
        if pool.state == "ready" and not pool.serving():
            health = Health(status="starting", detail="no solver worker is alive: their "
                            "replacements are warming up")
        return JSONResponse(health.model_dump(), status_code=200 if health.status == "ready"
                            else 503)

    @app.get("/metrics", name="metrics", response_class=PlainTextResponse, tags=["operations"],
             summary="Prometheus metrics",
             responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                              "description": "Prometheus text exposition format."}})
    async def metrics_endpoint() -> Response:
        """Request counts and latencies by route and status, solves by outcome, solver
        failures, queue state, readiness."""
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    return app


app = create_app()
