"""The jobs endpoints (``/v1/jobs``): whole recordings or many tracks, reconstructed in the
background by :class:`service.jobs.JobRunner` (contract: ``../shared/spec/recordings.md``)."""

from __future__ import annotations

import codecs
import datetime as dt
import json
import os
import shutil
import time
from collections.abc import AsyncGenerator, Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import pyarrow as pa
from fastapi import APIRouter, FastAPI, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, TypeAdapter, ValidationError
from starlette.datastructures import UploadFile
from starlette.formparsers import MultiPartException, MultiPartParser
from starlette.middleware.gzip import DEFAULT_EXCLUDED_CONTENT_TYPES
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Receive, Scope, Send

from solver.inputs import Bounds, InputError
from solver.io.dates import UTC, iso_utc, midnight_us
from solver.io.reading import RECORDING_HEAD_BYTES, check_not_compressed, check_recording_head
from solver.io.sensors_file import SensorSet, parse_sensors
from solver.io.split import recording_frame
from solver.io.tables import APART_NAME, PIECE_NAME, PlotRows, write_table
from solver.json_keys import TWICE, duplicate_key
from solver.manoeuvres import from_segment_rows
from solver.run_settings import RunSettings
from solver.sensors import RadarSensor

from .admission import BuildSlots, ByteBudget, Crowded, Gone
from .convert import plot_table, require_fields, unsent_reference
from .job_figures import Busy, TrackFigures
from .job_models import (
    JobOptions,
    JobStatus,
    JobTrack,
    JobTrackResult,
    JobTracksRequest,
    SensorSummaryOut,
)
from .jobs import FINISHED, RESULT_FILES, Full, JobRecord, JobRunner
from .models import ErrorResponse, PlotIn, shortened
from .settings import Settings

JOBS_PATH = "/v1/jobs"
HEAD_ONLY = "trajrecon.head_only"
"""Scope key set on a ``HEAD`` served as ``GET`` (:class:`service.app.HeadAsGet`): a file
answer then sends its headers without reading the file."""
MAX_TRACK_KEY_CHARS = 200
"""Longest name of a JSON job's track (the ``aircraft`` option's limit too)."""
TABLE_SUFFIXES = {".csv": ".csv", ".parquet": ".parquet", ".pq": ".parquet"}
MAX_SENSORS_PART = 16 << 20  # a sensor file sent as a plain form field (bytes)
_COV_NAMES = ("x", "z", "vx", "vz")
TRACK_COLUMNS = (*PlotIn.model_fields, "aircraft")
"""The plot table's columns a JSON job stores: every field of a request's plot (a list of its
own had left out `flight_level`: a Mode C track came out 655 m RMS instead of 49.6 m) and the
track's key."""


def _err(description: str) -> dict[str, Any]:
    return {"model": ErrorResponse, "description": description}


_NOT_FOUND = {404: _err("No such job (or track).")}
_NOT_YET = {409: _err("Not available in the job's (or track's) current state.")}
_CROWDED = {503: _err("Too many large answers being built; retry after `Retry-After` "
                      "seconds.")}
_PNG = {200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
              "description": "A PNG image."}}

router = APIRouter(tags=["jobs"])


class TooLarge(Exception):
    """An upload over ``jobs_max_upload_bytes``."""


class JobsBodyLimit:
    """The service's body limit (``limit``, e.g. :class:`service.app.BodyLimit`) for every
    request but ``POST /v1/jobs``, whose uploads the route limits itself (with its own 413, at
    ``jobs_max_upload_bytes``)."""

    def __init__(self, app: ASGIApp, limit: type, max_bytes: int):
        self.app = app
        self.limited = limit(app, max_bytes=max_bytes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (scope["type"] == "http" and scope["method"] == "POST"
                and scope["path"].rstrip("/") == JOBS_PATH):
            await self.app(scope, receive, send)
        else:
            await self.limited(scope, receive, send)


def install_jobs(app: FastAPI, settings: Settings) -> JobRunner:
    """Add the jobs routes to ``app``; the returned runner is started and closed by the
    application's lifespan."""
    runner = JobRunner(settings)
    app.state.jobs = runner
    app.state.job_figures = TrackFigures(runner, settings.jobs_figure_draws)
    app.state.answer_slots = BuildSlots(settings.jobs_answer_builds,
                                        settings.jobs_answer_waiting)
    app.state.json_bytes = ByteBudget(settings.jobs_json_bytes_in_flight,
                                      "JSON bodies of tracks")
    app.include_router(router)
    return runner


def _runner(request: Request) -> JobRunner:
    """The app's job runner; 503 while its store is not open (the reason in the message)."""
    runner: JobRunner = request.app.state.jobs
    if runner.store is None:
        raise HTTPException(503, f"jobs are unavailable: {runner.unavailable}",
                            headers={"Retry-After": str(runner.settings.retry_after_s)})
    return runner


def _error(status: int, message: str, loc: list[str | int] | None = None,
           headers: dict[str, str] | None = None) -> JSONResponse:
    detail = [] if loc is None else [{"loc": loc, "msg": message, "type": "value_error"}]
    body = ErrorResponse.model_validate({"message": message, "detail": detail})
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


def _busy(runner: JobRunner, why: str, what: str = "too many jobs") -> JSONResponse:
    return _error(503, f"{what}: {why}; retry later",
                  headers={"Retry-After": str(runner.settings.retry_after_s)})


# ----------------------------------------------------------------------------------- create


def _schema(model: type[BaseModel]) -> dict[str, Any]:
    """``model``'s JSON schema inline, its parts referring to the document's components."""
    return {k: v for k, v in model.model_json_schema(
        ref_template="#/components/schemas/{model}").items() if k != "$defs"}


_CREATE_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {"schema": {
            "type": "object", "required": ["recording", "sensors"],
            "properties": {
                "recording": {"type": "string", "format": "binary", "description":
                              "The recording: raw ASTERIX (CAT048/021/034), an IOSS (FINAL) "
                              "recording or a pcap or pcapng capture of it, or a plot table "
                              "(.csv or .parquet; the file name's suffix or the content tells "
                              "which)."},
                "sensors": {"type": "string", "format": "binary", "description":
                            "The sensor file (JSON, recordings.md): a file part or a text "
                            "field."},
                "options": {**_schema(JobOptions), "description":
                            "Optional, as JSON (a text field or a file part): the bounds "
                            "and the recursive filters for every track, e.g. "
                            "`{\"filters\": [\"imm_smoother\"]}`."}}},
            "encoding": {"options": {"contentType": "application/json"}}},
        "application/json": {"schema": _schema(JobTracksRequest)},
    },
}


@router.post(JOBS_PATH, status_code=202, response_model=JobStatus,
             summary="Reconstruct a whole recording (or many tracks) in the background",
             openapi_extra={"requestBody": _CREATE_BODY},
             responses={202: {"headers": {"Location": {
                            "description": "The job's URL.", "schema": {"type": "string"}}}},
                        413: _err("Upload over the jobs' size limit."),
                        415: _err("Neither multipart/form-data nor JSON, or a Content-Encoding "
                                 "other than identity."),
                        422: _err("Invalid input; the message names the part or field."),
                        503: _err("Too many jobs queued, running or being received, or too "
                                  "many bytes of JSON bodies being received and checked "
                                  "(`jobs_json_bytes_in_flight`); retry after `Retry-After` "
                                  "seconds.")})
async def create_job(request: Request) -> Response:
    """Accept a job: a multipart upload of a `recording` file and its `sensors` file, or a
    JSON body of tracks (`JobTracksRequest`). The inputs are stored durably before the 202;
    the job runs in the background (`GET` its `Location` for progress). A recording whose
    content cannot be read is accepted and ends `failed` with the reason; partial problems
    (damaged blocks, unknown sensors, short tracks) are counted in the job's `problems`."""
    runner = _runner(request)
    try:
        runner.check_room()
    except Full as e:
        return _busy(runner, str(e))
    limit = runner.settings.jobs_max_upload_bytes
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == "application/json":  # validated in memory: its own, smaller limit
        limit = min(limit, runner.settings.jobs_max_json_bytes)
    length = request.headers.get("content-length", "")
    if length.isdigit() and int(length) > limit:
        return _too_large(limit, ctype)
    if ctype not in ("multipart/form-data", "application/json"):
        return _error(415, "send the recording as multipart/form-data (parts `recording` and "
                      "`sensors`) or the tracks as application/json", ["headers",
                                                                       "content-type"])
    reserved = ((int(length) if length.isdigit() else limit) if ctype == "application/json"
                else 0)  # a multipart upload streams to disk
    budget: ByteBudget = request.app.state.json_bytes
    try:
        with runner.receiving():
            budget.reserve(reserved)
            try:
                record = await _receive(request, runner, ctype, limit)
            finally:
                budget.release(reserved)
    except TooLarge:
        return _too_large(limit, ctype)
    except Full as e:
        return _busy(runner, str(e))
    except Crowded as e:
        return _busy(runner, str(e), "too many JSON bodies at once")
    body_out = _status(runner, record)
    return JSONResponse(body_out.model_dump(mode="json"), status_code=202,
                        headers={"Location": f"{JOBS_PATH}/{record.id}"})


async def _receive(request: Request, runner: JobRunner, ctype: str, limit: int) -> JobRecord:
    """Read, check and store a post's inputs, then queue its job."""
    incoming = await run_in_threadpool(runner.new_inputs)
    accepted = False
    try:
        if ctype == "multipart/form-data":
            kind = "recording"
            await _save_upload(request, incoming / "inputs", limit)
        else:
            kind = "tracks"
            body = b"".join([c async for c in _limited(request, limit)])
            await run_in_threadpool(_save_tracks, body, incoming / "inputs",
                                    runner.settings.jobs_max_tracks)
            del body
        record = await run_in_threadpool(runner.accept, incoming, kind)
        accepted = True
    finally:
        if not accepted:
            shutil.rmtree(incoming, ignore_errors=True)
    return record


def _too_large(limit: int, ctype: str = "") -> JSONResponse:
    if ctype == "application/json":
        return _error(413, f"request body is larger than the jobs' limit of {limit} bytes for "
                      "a JSON body of tracks (jobs_max_json_bytes: validating JSON takes about "
                      "14 times its size in memory); send the plots as a CSV or Parquet table "
                      "(multipart/form-data, part `recording`) instead")
    return _error(413, f"request body is larger than the jobs' upload limit of {limit} bytes")


async def _limited(request: Request, limit: int) -> AsyncGenerator[bytes, None]:
    received = 0
    async for chunk in request.stream():
        received += len(chunk)
        if received > limit:
            raise TooLarge
        yield chunk


async def _save_upload(request: Request, inputs: Path, limit: int) -> None:
    """Stream the multipart body (counted against ``limit``) and store its two parts."""
    parser = MultiPartParser(request.headers, _limited(request, limit), max_files=4,
                             max_fields=4, max_part_size=MAX_SENSORS_PART)
    try:
        form = await parser.parse()
    except MultiPartException as e:
        raise InputError(("body",), f"is not a valid multipart/form-data body: {e.message}"
                         ) from None
    try:
        unknown = sorted(set(form.keys()) - {"recording", "sensors", "options"})
        if unknown:
            raise InputError((unknown[0],), "is not a part of a job upload (parts: recording, "
                             "sensors, options)")
        twice = next((name for name in form if len(form.getlist(name)) > 1), None)
        if twice is not None:  # otherwise the last one would win, unseen
            raise InputError((twice,), "is given twice: send one part of each name")
        recording, sensors = form.get("recording"), form.get("sensors")
        if not isinstance(recording, UploadFile):
            raise InputError(("recording",), "is required: a file part with the recording "
                             "(raw ASTERIX, IOSS/FINAL, pcap, pcapng, CSV or Parquet)")
        if sensors is None:
            raise InputError(("sensors",), "is required: the sensor file (JSON) as a file "
                             "part or a text field")
        text = await _text(sensors)
        options = _options(await _text(form.get("options")))
        await run_in_threadpool(_store_upload, recording, text, options, inputs)
    finally:
        await form.close()


async def _text(part: UploadFile | str | None) -> str | None:
    if part is None:
        return None
    return (await part.read()).decode("utf-8", "replace") if isinstance(part, UploadFile) \
        else str(part)


def _options(text: str | None) -> JobOptions:
    """The upload's ``options`` part (none: the defaults); 422 located under ``options``."""
    if text is None:
        return JobOptions()
    twice = duplicate_key(text)
    if twice is not None:
        raise InputError(("options", *twice), TWICE)
    try:
        return JobOptions.model_validate_json(text)
    except ValidationError as e:
        errors = e.errors(include_url=False)
        syntax = next((err for err in errors if err["type"] == "json_invalid"), None)
        if syntax is not None:  # pydantic's message says where (line and column)
            raise InputError(("options",), "is not valid JSON: "
                             f"{(syntax.get('ctx') or {}).get('error', syntax['msg'])}"
                             ) from None
        raise RequestValidationError([{**err, "loc": ("body", "options", *err["loc"])}
                                      for err in errors]) from None


def _params(options: JobOptions | JobTracksRequest, aircraft: list[str] | None = None) -> str:
    """``params.json``: the job's :class:`solver.run_settings.RunSettings` (what its run reads,
    :meth:`service.jobs.JobRunner.options`) and the aircraft asked for
    (:meth:`service.jobs.JobRunner.aircraft`); the bounds and windows are checked here as the
    reconstruction would (422 at ``bounds.<name>``, ``window.<name>``)."""
    b, w = options.bounds, options.window
    box = Bounds(u=tuple(b.u), w=tuple(b.w), v=tuple(b.v))  # type: ignore[arg-type]
    settings = RunSettings(method=options.method, bounds=box, filters=tuple(options.filters),
                           filter_gate_sigma=options.filter_gate_sigma,
                           sample_step_s=options.sample_step_s,
                           window_plots=RunSettings.window_plots if w.plots is None else w.plots,
                           trial_step_s=w.trial_step_s, criterion=options.criterion,
                           editions=tuple((int(cat), name) for cat, name in
                                          getattr(options, "editions", {}).items()),
                           date=getattr(options, "date", None))
    settings.config().validate()
    doc = settings.as_json()
    if aircraft:
        doc["aircraft"] = aircraft
    return json.dumps(doc)


def _store_upload(recording: UploadFile, sensors_text: str, options: JobOptions,
                  inputs: Path) -> None:
    twice = duplicate_key(sensors_text)
    if twice is not None:
        raise InputError(("sensors", *twice), TWICE)
    parse_sensors(sensors_text)  # 422 at sensors[j].field for a bad sensor file
    try:
        params = _params(options, options.aircraft)
    except InputError as e:
        raise InputError(("options", *e.loc), e.message) from None
    src = recording.file
    src.seek(0)
    head = src.read(RECORDING_HEAD_BYTES)
    if not head:
        raise InputError(("recording",), "is empty")
    check_not_compressed(head)  # whatever its name: a gzip read as CAT031 blocks, or a table
    if _looks_like_json(head):  # a compact one was taken for a CSV header ("," and "sensor"),
        # accepted, then failed as a table
        try:
            check_recording_head(head)
        except InputError as e:
            raise InputError(e.loc, f"{e.message}; it is JSON: plots as JSON are a job's "
                             "application/json body of tracks") from None
    suffix = TABLE_SUFFIXES.get(Path(recording.filename or "").suffix.lower())
    if suffix is None:
        suffix = ".parquet" if head[:4] == b"PAR1" else ".csv" if _looks_like_csv(head) \
            else ".ast"
    if suffix == ".ast":  # a JSON or text file read as ASTERIX: one line, not CAT123 blocks
        check_recording_head(head)
    src.seek(0)
    with open(inputs / f"recording{suffix}", "wb") as f:
        shutil.copyfileobj(src, f, 1 << 20)
    (inputs / "sensors.json").write_text(sensors_text, encoding="utf-8")
    (inputs / "params.json").write_text(params + "\n", encoding="utf-8")


def _looks_like_json(head: bytes) -> bool:
    """UTF-8 text (the head may end inside a character) whose first non-blank character opens
    a JSON object or array (a table's header line names columns; ASTERIX has no categories
    123 and 91)."""
    try:
        text = codecs.getincrementaldecoder("utf-8-sig")().decode(head, final=False)
    except UnicodeDecodeError:
        return False
    return text.lstrip(" \t\r\n")[:1] in ("{", "[")


def _looks_like_csv(head: bytes) -> bool:
    """A text header line naming the table's columns (the table's spec)."""
    try:
        first = head.decode("utf-8").splitlines()[0]
    except (UnicodeDecodeError, IndexError):
        return False
    return "," in first and "sensor" in first


def _save_tracks(body: bytes, inputs: Path, max_tracks: int) -> None:
    """Validate a JSON body of at most ``max_tracks`` tracks and store it as a plot table with
    its sensor file."""
    twice = duplicate_key(body)  # a track name twice: one track would be silently lost
    if twice is not None:
        raise InputError(twice, TWICE)
    try:
        req = JobTracksRequest.model_validate_json(body)
    except ValidationError as e:
        raise RequestValidationError(e.errors(include_url=False), body=body) from None
    doc: dict[str, Any] = {"sensors": [_sensor_doc(s) for s in req.sensors]}
    if req.reference is not None:
        doc["reference"] = req.reference.model_dump()
    sensors = parse_sensors(doc)
    params = _params(req)
    radar = {s.id: isinstance(s, RadarSensor) for s in sensors.sensors}
    cols: dict[str, list[Any]] = {k: [] for k in TRACK_COLUMNS}
    if len(req.tracks) > max_tracks:
        raise InputError(("tracks",), f"has {len(req.tracks)} tracks; a job may hold at most "
                         f"{max_tracks} (TRAJRECON_JOBS_MAX_TRACKS)")
    for key, plots in req.tracks.items():
        if not key.strip():
            raise InputError(("tracks",), "has an empty key: every track needs a name")
        if len(key) > MAX_TRACK_KEY_CHARS or not key.isprintable():
            raise InputError(("tracks", key[:40]), f"is not a track name: at most "
                             f"{MAX_TRACK_KEY_CHARS} printable characters (as the aircraft "
                             "option's)")
        if key != key.strip():  # the plot table's aircraft column is read stripped: "B1 "
            # merged into "B1" with no word (a hostile-client tester's)
            raise InputError(("tracks", key[:40]), "is not a track name: it may not begin or "
                             "end with white space (it would be the track without it)")
        if {".", ".."} & set(key.split("/")):  # clients normalise such path segments away
            raise InputError(("tracks", key[:40]), "is not a track name: '.' and '..' are "
                             "path segments clients resolve before sending the track's URL")
        if key.endswith("/figure.png"):  # its URL would be another track's figure
            raise InputError(("tracks", key[:40]), "is not a track name: it may not end in "
                             "/figure.png (the track figure's path)")
        if PIECE_NAME.search(key) or APART_NAME.search(key):  # it would merge with another
            # key's piece after a gap, or (the table's reader refuses both) be dropped whole
            raise InputError(("tracks", key[:40]), "is not a track name: it may not end in "
                             "#<number> or ~<number> (the names of a track's piece after a "
                             "time gap and of another aircraft found under its key)")
        if not plots:
            raise InputError(("tracks", key), "has no plots (a track needs at least 3)")
        for i, p in enumerate(plots):
            loc: tuple[str | int, ...] = ("tracks", key, i)
            if p.sensor is None:
                raise InputError((*loc, "sensor"), "is required (one of the `sensors` ids)")
            if p.sensor not in radar:
                raise InputError((*loc, "sensor"), f"{p.sensor!r} is not a sensor id (ids: "
                                 f"{', '.join(radar)})")
            require_fields(p, "radar" if radar[p.sensor] else "position", loc)
            for name in cols:
                value = key if name == "aircraft" else getattr(p, name)
                cols[name].append(np.nan if value is None else value)
    n = len(cols["t"])
    rows = PlotRows.from_columns(n, **{k: np.asarray(v, dtype=object if k in (
        "sensor", "aircraft") else float) for k, v in cols.items()})
    _check_tracks(req, sensors, rows)
    write_table(rows, inputs / "recording.parquet")
    (inputs / "sensors.json").write_text(json.dumps(doc), encoding="utf-8")
    (inputs / "params.json").write_text(params + "\n", encoding="utf-8")


def _sensor_doc(s: BaseModel) -> dict[str, Any]:
    """A request sensor as the sensor file's object: the site's default `height_m` left out
    of a radar without a site (the file refuses a height without a site; a client that gave
    one gets that 422)."""
    doc = s.model_dump(exclude_none=True)
    if "lat_deg" not in doc and "height_m" not in s.model_fields_set:
        doc.pop("height_m", None)
    return doc


def _check_tracks(req: JobTracksRequest, sensors: SensorSet, rows: PlotRows) -> None:
    """Each track's plots checked as the single-track endpoint checks its plots, in the
    plane the job reconstructs them in (422 at ``tracks.<key>[i].<field>``): the job's reading
    would leave the bad ones out, reported at a row of all tracks joined."""
    frame = recording_frame(sensors, rows)
    if frame is not None and sensors.reference is None:
        try:
            frame.validate()
        except InputError as e:
            first = next((("tracks", key, i) for key, plots in req.tracks.items()
                          for i, p in enumerate(plots)
                          if p.lat_deg is not None and p.lon_deg is not None), ("tracks",))
            raise unsent_reference(e, sensors.sensors, first) from None
    index = sensors.index()
    for key, plots in req.tracks.items():
        used = sorted({index[p.sensor] for p in plots if p.sensor is not None})
        plot_table([sensors.sensors[k] for k in used], plots, frame, ("tracks", key))


# ------------------------------------------------------------------------------------- read


def _iso(t: float | None) -> str | None:
    return None if t is None else dt.datetime.fromtimestamp(t, dt.UTC).isoformat()


def _status(runner: JobRunner, job: JobRecord) -> JobStatus:
    p = runner.progress(job.id)
    end = job.finished if job.state in FINISHED else time.time()
    return JobStatus(
        id=job.id, kind=job.kind, state=job.state,  # type: ignore[arg-type]
        tracks_total=job.tracks_total, tracks_done=p.done, tracks_failed=p.failed,
        plots=job.plots, plots_done=p.plots_done, rows=job.rows,
        problems=job.problems,  # type: ignore[arg-type]
        error=job.error, created=_iso(job.created) or "", started=_iso(job.started),
        finished=_iso(job.finished),
        elapsed_s=None if job.started is None or end is None else max(end - job.started, 0.0),
        runs=job.runs, input_bytes=job.input_bytes,
        options=_options_out(runner.options(job.id), runner.aircraft(job.id))
        if runner.job_dir(job.id).is_dir()
        else None)


def _options_out(settings: RunSettings, aircraft: list[str] | None) -> dict[str, Any]:
    return {**settings.as_json(), "aircraft": aircraft}


class _OpenFile(FileResponse):
    """A :class:`FileResponse` of a file opened before the answer (Range, ETag and
    Last-Modified as FileResponse's), served through ``/proc/self/fd``: a DELETE of its job
    while it is sent (which unlinks it) no longer turns the answer into a 500 (a
    hostile-client tester's: figure, zip and Parquet reads racing a DELETE). The descriptor is
    closed when the answer ends, sent or not."""

    def __init__(self, fd: int, **kwargs: Any):
        super().__init__(f"/proc/self/fd/{fd}", **kwargs)
        self.fd = fd

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope.get(HEAD_ONLY) and not _gzipped(scope, self.media_type):
            scope = {**scope, "method": "HEAD"}  # a HEAD served as GET: the file unread
        try:
            await super().__call__(scope, receive, send)
        finally:
            os.close(self.fd)


def _gzipped(scope: Scope, media_type: str | None) -> bool:
    """Whether the service's gzip compresses this answer (the client takes gzip, the type is
    not one it leaves alone): a HEAD must then say the compressed length, so the file is read
    as for a GET."""
    accepts = b"gzip" in dict(scope["headers"]).get(b"accept-encoding", b"")
    kind = (media_type or "").partition(";")[0].strip().lower()
    return accepts and not {kind, kind.partition("/")[0] + "/*"} & set(
        DEFAULT_EXCLUDED_CONTENT_TYPES)


def _file(path: Path, media_type: str, filename: str | None = None) -> Response:
    """The file at ``path`` (gone before it is opened: a FileNotFoundError, 404 when its job
    was deleted meanwhile)."""
    if not Path("/proc/self/fd").is_dir():  # not Linux: the path itself
        return FileResponse(path, media_type=media_type, filename=filename)
    return _OpenFile(os.open(path, os.O_RDONLY), media_type=media_type, filename=filename)


def _job(runner: JobRunner, job_id: str) -> JobRecord:
    job = runner.get(job_id)
    if job is None:
        raise HTTPException(404, f"job {shortened(job_id)} not found")
    return job


MAX_LISTED_TRACKS = 10_000
"""At most this many tracks in one ``GET /v1/jobs/{id}/tracks`` (the default: one page)."""
MAX_LISTED_JOBS = 500
"""At most this many jobs in one ``GET /v1/jobs`` (the cost of a listing is bounded)."""


@router.get(JOBS_PATH, response_model=list[JobStatus], summary="The service's jobs, newest first")
def list_jobs(request: Request,
              limit: Annotated[int, Query(ge=1, le=MAX_LISTED_JOBS,
                                          description="At most this many jobs.")] = 50,
              state: Annotated[Literal["queued", "running", "done", "failed", "cancelled"]
                               | None, Query(description="Only jobs in this state.")] = None
              ) -> list[JobStatus]:
    """Every job the service keeps (until deleted), newest first, each as ``GET
    /v1/jobs/{id}`` gives it: to find a job whose id was lost, or what is still running (a
    walkthrough helper found no way to)."""
    runner = _runner(request)
    return [_status(runner, job) for job in runner.recent(limit, state)]


@router.get(JOBS_PATH + "/{job_id}", response_model=JobStatus, responses=_NOT_FOUND,
            summary="A job's state and progress")
def get_job(job_id: str, request: Request) -> JobStatus:
    """State (queued, running, done, failed, cancelled), tracks done/failed/total, plots, the
    input's problems and timing."""
    runner = _runner(request)
    return _status(runner, _job(runner, job_id))


@router.delete(JOBS_PATH + "/{job_id}", response_model=JobStatus,
               responses={**_NOT_FOUND, 204: {"description": "The finished job and its data "
                                                             "were removed."}},
               summary="Cancel a job (or remove a finished one)")
def delete_job(job_id: str, request: Request) -> Response:
    """A queued or running job is cancelled (200 with its status, at once: its tracks in
    flight are dropped, its finished tracks stay readable until it is deleted, and the
    whole-job results of those follow in a few seconds, 409 until then); a finished job
    (done, failed, cancelled) is removed with its data (204; a job cancelled a moment ago,
    still writing those results, answers 200 with its status until it has)."""
    runner = _runner(request)
    _job(runner, job_id)
    job = runner.cancel(job_id)
    if job is None:
        return Response(status_code=204)
    return JSONResponse(_status(runner, job).model_dump(mode="json"))


async def _built(request: Request, fn: Callable[..., bytes], *args: Any) -> bytes:
    """``fn(*args)``, a large answer's JSON, built in the threadpool when one of the build
    slots is free (:class:`service.admission.BuildSlots`); 503 with Retry-After when too
    many wait. Rendered there too: FastAPI renders a returned model on the event loop (0.3 s
    for 19.6 MB)."""
    slots: BuildSlots = request.app.state.answer_slots
    try:
        return await slots.build(fn, *args, gone=request.is_disconnected)
    except Gone:  # nobody reads an answer: 499 and an info line (the app's handler)
        raise ClientDisconnect() from None
    except Crowded as e:
        raise HTTPException(503, f"too many large answers at once: {e}; retry later", headers={
            "Retry-After": str(request.app.state.settings.retry_after_s)}) from None


_TRACK_LIST = TypeAdapter(list[JobTrack])


@router.get(JOBS_PATH + "/{job_id}/tracks", response_model=list[JobTrack],
            responses={**_NOT_FOUND, **_CROWDED}, summary="A job's tracks with their status")
async def list_job_tracks(job_id: str, request: Request,
                    offset: Annotated[int, Query(ge=0, description="Tracks to pass over "
                                                 "first.")] = 0,
                    limit: Annotated[int, Query(ge=1, le=MAX_LISTED_TRACKS, description=(
                        "At most this many tracks (the job's `tracks_total` tells how many "
                        "there are)."))] = MAX_LISTED_TRACKS) -> Response:
    """The aircraft of the job (empty until the recording has been read), in order of first
    plot: pending, done or failed (with the reason); ``offset`` and ``limit`` page through a
    job of many (a tester's 300,000 tracks made one answer of 29 MB in 5.5 s)."""
    runner = _runner(request)
    body, total = await _built(request, _track_list, runner, job_id, offset, limit)
    return Response(body, media_type="application/json",  # a page says it is one
                    headers={"X-Total-Count": str(total)})


def _track_list(runner: JobRunner, job_id: str, offset: int, limit: int) -> tuple[bytes, int]:
    """The JSON of a page of a job's tracks, and the job's count of tracks."""
    job = _job(runner, job_id)
    unfinished = "cancelled" if job.state == "cancelled" else "pending"
    entries = runner.progress(job_id).entries
    out = []
    for key, plots in runner.tracks(job_id, offset, limit):
        e = entries.get(key)
        out.append(JobTrack(aircraft=key, plots=plots, status=unfinished) if e is None else
                   JobTrack(aircraft=key, plots=plots, status=e["status"], error=e["error"],
                            elapsed_s=e.get("elapsed_s"), warnings=e.get("warnings") or []))
    return _TRACK_LIST.dump_json(out, by_alias=True), job.tracks_total or 0


# ``{aircraft:path}``: a key may hold "/" (a user's own key); the figure's route comes first


def _track_entry(runner: JobRunner, job_id: str, aircraft: str) -> tuple[str, dict[str, Any]]:
    """The key of the done track ``aircraft`` (exactly, else the one key equal to it but for
    case) and its ledger entry; 404 (no such track), 409 (pending or failed)."""
    _job(runner, job_id)
    keys = runner.track_keys(job_id, aircraft)
    if len(keys) != 1:
        similar = (f" ({len(keys)} tracks differ from it only in case: "
                   f"{', '.join(map(repr, keys[:5]))})" if keys else "")
        raise HTTPException(404, f"job {job_id} has no track {shortened(aircraft)!r}{similar}")
    key = keys[0]
    entry = runner.progress(job_id).entries.get(key)
    if entry is None:
        _job(runner, job_id)  # deleted meanwhile: 404, not pending
        raise HTTPException(409, f"track {key!r} is not reconstructed yet (pending)")
    if entry["status"] != "done":
        raise HTTPException(409, f"track {key!r} failed: {entry['error']}")
    return key, entry


@router.get(JOBS_PATH + "/{job_id}/tracks/{aircraft:path}/figure.png", response_class=Response,
            responses={**_PNG, **_NOT_FOUND, **_NOT_YET,
                       503: _err("As many figures as the service draws at once are being "
                                 "drawn; retry after `Retry-After` seconds.")},
            summary="A job track's figure")
async def get_job_track_figure(job_id: str, aircraft: str, request: Request) -> Response:
    """The track's plots with their ellipses, the reconstruction and its controls over time;
    drawn when first asked for (as soon as the track is done, from what the job stored of
    it), then kept with the job. A figure not drawn yet while the service draws as many as it
    may at once (`jobs_figure_draws`) is 503 with `Retry-After`."""
    runner = _runner(request)
    key, _ = await run_in_threadpool(_track_entry, runner, job_id, aircraft)
    figures: TrackFigures = request.app.state.job_figures
    try:
        path = await figures.path(job_id, key)
    except Busy as e:
        return _error(503, f"too many figures being drawn: {e}; retry later",
                      headers={"Retry-After": str(runner.settings.retry_after_s)})
    if path is None:
        raise HTTPException(404, f"no figure of track {key!r}: its job kept nothing to draw "
                            "it from (track figures were off: jobs_track_figures)")
    return await run_in_threadpool(_file, path, "image/png")


@router.get(JOBS_PATH + "/{job_id}/tracks/{aircraft:path}", response_model=JobTrackResult,
            responses={**_NOT_FOUND, **_NOT_YET, **_CROWDED},
            summary="One reconstructed track of a job")
async def get_job_track(job_id: str, aircraft: str, request: Request,
                  omit: Annotated[list[Literal["samples", "covariances"]], Query(
                      max_length=2, description="Parts of the answer to leave out, as in "
                      "`POST /v1/reconstructions`: `samples` (an empty `trajectory.samples`) "
                      "and/or `covariances` (every `cov` null), e.g. "
                      "`?omit=samples&omit=covariances`.")] = []  # noqa: B006 - not mutated
                  ) -> Response:
    """The track's segments and its state at every plot (with latitude and longitude), the
    regular samples when the job keeps them, the filters' states, its sensors' statistics and
    the reconstruction's diagnostics; available as soon as the track is done. `aircraft`: the
    track's key, exactly, else in another case when only one key matches (`4ca2d1`)."""
    runner = _runner(request)
    body = await _built(request, _track_answer, runner, job_id, aircraft, frozenset(omit))
    return Response(body, media_type="application/json")


def _track_answer(runner: JobRunner, job_id: str, aircraft: str, omit: frozenset[str]
                  ) -> bytes:
    """The JSON of a done track's :class:`JobTrackResult`."""
    key, entry = _track_entry(runner, job_id, aircraft)
    got = runner.track_rows(job_id, key, samples="samples" not in omit)
    if got is None:  # pragma: no cover - a done entry always names its part
        raise HTTPException(409, f"track {key!r} has no stored rows")
    states, segments, filtered, sampled = got
    cov = "covariances" not in omit
    midnight = midnight_us(states)
    return JobTrackResult.model_validate({
        "aircraft": key,
        "trajectory": {"segments": _with_utc(_segment_rows(segments), midnight),
                       "manoeuvres": _with_utc([m.as_dict() for m in
                                                from_segment_rows(segments)], midnight),
                       "at_plots": _state_rows(states, cov),
                       "samples": [] if sampled is None else _sample_rows(sampled, cov),
                       **_altitude(entry.get("altitude"))},
        "sensors": [_sensor_out(r) for r in runner.track_sensors(job_id, key)],
        "filters": _filter_rows(filtered, cov),
        "diagnostics": _track_diagnostics(entry)}).model_dump_json(by_alias=True).encode()


def _with_utc(rows: list[dict[str, Any]], midnight: int | None) -> list[dict[str, Any]]:
    """Segments or manoeuvres with ``time_utc_start`` / ``time_utc_end`` beside ``t_start`` /
    ``t_end`` (null without the date)."""
    for end in ("start", "end"):
        stamps = None if midnight is None or not rows else iso_utc(pa.array(
            [midnight + round(r[f"t_{end}"] * 1e6) for r in rows], pa.int64()).cast(UTC)
        ).to_pylist()
        for i, r in enumerate(rows):
            r[f"time_utc_{end}"] = None if stamps is None else stamps[i]
    return rows


def _altitude(got: dict[str, float] | None) -> dict[str, float]:
    return {} if got is None else {"altitude_m": got["m"], "altitude_sigma_m": got["sigma_m"]}


def _track_diagnostics(entry: dict[str, Any]) -> dict[str, Any]:
    """A done track's ledger line -> the answer's ``diagnostics``."""
    task_ms = 1e3 * float(entry.get("elapsed_s") or 0.0)
    return {"elapsed_ms": task_ms, **(entry.get("diagnostics") or {}), "task_ms": task_ms,
            "warnings": entry.get("warnings") or []}


def _state_rows(t: Any, cov: bool = True) -> list[dict[str, Any]]:
    """``tracks.parquet`` rows of one track: :func:`_sample_rows` with each plot's index,
    sensor and residuals (those it has)."""
    cols = t.to_pydict()
    out = _sample_rows(t, cov, cols)
    for i, row in enumerate(out):
        row["plot"], row["sensor"] = cols["plot"][i], cols["sensor"][i]
        if cols.get("source") is not None and cols["source"][i] is not None:
            row["source"] = cols["source"][i]
        for name in ("range_residual_m", "azimuth_residual_deg", "position_residual_m",
                     "along_track_residual_m", "cross_track_residual_m", "gated"):
            if cols.get(name) is not None and cols[name][i] is not None:
                row[name] = cols[name][i]
    return out


def _sample_rows(t: Any, cov: bool = True, cols: dict[str, list[Any]] | None = None
                 ) -> list[dict[str, Any]]:
    """States of one track (``samples.parquet``, or ``tracks.parquet`` with ``cols`` its
    columns already read): kinematics, the covariance unless ``cov`` is false, the height
    where it was estimated."""
    cols = t.to_pydict() if cols is None else cols
    utc = (iso_utc(t.column("time_utc")).to_pylist() if "time_utc" in t.column_names
           else [None] * t.num_rows)  # a part stored before the column: null
    out = []
    for i in range(t.num_rows):
        row = {k: cols[k][i] for k in ("t", "x", "z", "vx", "vz", "speed", "heading_deg",
                                       "lat_deg", "lon_deg")}
        row["time_utc"] = utc[i]
        row["heading_deg"] = row["heading_deg"] % 360.0
        row["cov"] = _cov(cols, i) if cov else None
        if cols["h_m"][i] is not None and cols["h_sigma_m"][i] is not None:
            row["altitude_m"], row["altitude_sigma_m"] = cols["h_m"][i], cols["h_sigma_m"][i]
        out.append(row)
    return out


def _cov(cols: dict[str, list[Any]], i: int) -> list[list[Any]] | None:
    """Row ``i``'s covariance over ``(x, z, vx, vz)`` from its upper triangle; None when a
    term is not finite."""
    cov = [[0.0] * 4 for _ in range(4)]
    for a in range(4):
        for b in range(a, 4):
            v = cols[f"cov_{_COV_NAMES[a]}_{_COV_NAMES[b]}"][i]
            if v is None or not np.isfinite(v):
                return None
            cov[a][b] = cov[b][a] = v
    return cov


def _filter_rows(t: Any, cov: bool = True) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """``filters.parquet`` rows of one track -> ``{name: {"states": [...]}}`` in plot order."""
    if t is None:
        return {}
    cols = t.to_pydict()
    gated_col = cols.get("gated") or [False] * t.num_rows  # parts written before the column
    utc = (iso_utc(t.column("time_utc")).to_pylist() if "time_utc" in t.column_names
           else [None] * t.num_rows)  # a part stored before the column: null
    out: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    gated: dict[str, list[int]] = {}
    for i in range(t.num_rows):
        row = {k: cols[k][i] for k in ("t", "x", "z", "vx", "vz", "lat_deg", "lon_deg")}
        row["time_utc"] = utc[i]
        row["cov"] = _cov(cols, i) if cov else None
        out.setdefault(cols["filter"][i], []).append((cols["plot"][i], row))
        if gated_col[i]:
            gated.setdefault(cols["filter"][i], []).append(cols["plot"][i])
    return {name: {"states": [r for _, r in sorted(rows, key=lambda p: p[0])],
                   "gated": sorted(gated.get(name, []))}
            for name, rows in out.items()}


def _segment_rows(t: Any) -> list[dict[str, Any]]:
    cols = t.to_pydict()
    rows = [{k: cols[k][i] for k in ("t_start", "t_end", "u", "w", "x", "z", "heading_deg",
                                     "speed")} for i in range(t.num_rows)]
    for r in rows:
        r["heading_deg"] %= 360.0
    return rows


def _sensor_out(r: dict[str, Any]) -> dict[str, Any]:
    """A sensor report in degrees (the worker's dict carries radians)."""
    out = {k: v for k, v in r.items() if not k.endswith("_rad")}
    for k, v in r.items():
        if k.endswith("_rad"):
            out[k[:-4] + "_deg"] = None if v is None else float(np.rad2deg(v))
    return out


def _finished(runner: JobRunner, job_id: str) -> JobRecord:
    """A done job, or a failed one that ran to its end (no track reconstructed: its summary,
    problems and failures are there to read); else 409."""
    job = _job(runner, job_id)
    if job.state != "done" and not (job.state in ("failed", "cancelled")
                                    and runner.result_file(job_id, "summary.json")):
        raise HTTPException(409, f"job {job_id} is {job.state}; whole-job results are made "
                            "when it is done, or cancelled after finishing a track (finished "
                            "tracks: GET .../tracks/{aircraft})")
    return job


@router.get(JOBS_PATH + "/{job_id}/map.png", response_class=Response,
            responses={**_PNG, **_NOT_FOUND, **_NOT_YET}, summary="Map of a job's tracks")
def get_job_map(job_id: str, request: Request) -> Response:
    """Every reconstructed track of a done job on one map, with the radar sites."""
    runner = _runner(request)
    _finished(runner, job_id)
    path = runner.result_file(job_id, "map.png")
    if path is None:
        raise HTTPException(404, f"job {job_id} has no reconstructed track to map")
    return _file(path, "image/png")


@router.get(JOBS_PATH + "/{job_id}/sensors.png", response_class=Response,
            responses={**_PNG, **_NOT_FOUND, **_NOT_YET},
            summary="A job's radar residuals by range and azimuth")
def get_job_sensors_figure(job_id: str, request: Request) -> Response:
    """Each radar's plots of a done job against the reconstruction: the range and azimuth
    residuals over slant range and azimuth, binned mean and sigma over a sample of the plots
    (wild ones marked)."""
    runner = _runner(request)
    _finished(runner, job_id)
    path = runner.result_file(job_id, "sensors.png")
    if path is None:
        raise HTTPException(404, f"job {job_id} has no radar plot against a reconstructed "
                            "track")
    return _file(path, "image/png")


@router.get(JOBS_PATH + "/{job_id}/sensors", response_model=list[SensorSummaryOut],
            responses={**_NOT_FOUND, **_NOT_YET}, summary="Per-sensor statistics of a job")
def get_job_sensors(job_id: str, request: Request) -> list[SensorSummaryOut]:
    """Each sensor over all tracks of a done job: plots, detection rate, wild plots, bias and
    sigma of the range and azimuth residuals (the radar assessment of SASS-C/TRES)."""
    runner = _runner(request)
    _finished(runner, job_id)
    path = runner.result_file(job_id, "sensors.json")
    rows = json.loads(path.read_text(encoding="utf-8")) if path else []
    return [SensorSummaryOut.model_validate(r) for r in rows]


_MEDIA = {".parquet": "application/vnd.apache.parquet", ".csv": "text/csv",
          ".geojsonl": "application/geo+json-seq", ".json": "application/json",
          ".txt": "text/plain", ".png": "image/png", ".zip": "application/zip"}


@router.get(JOBS_PATH + "/{job_id}/results/{name}", response_class=Response,
            responses={200: {"content": {m: {"schema": {"type": "string", "format": "binary"}}
                                         for m in dict.fromkeys(_MEDIA.values())},
                              "description": "The file (media type by its suffix)."},
                       **_NOT_FOUND, **_NOT_YET}, summary="A done job's result file")
def get_job_result(job_id: str, name: str, request: Request) -> Response:
    """`tracks.parquet` (states at every plot), `segments.parquet`, `filters.parquet` (the
    job's `filters`' states at every plot, when it asked for any), `samples.parquet` (every
    track's state every `sample_step_s`, when it asked for them), `tracks.csv`,
    `tracks.geojsonl` (one LineString per aircraft), `manoeuvres.csv` (every track's turns and
    speed changes, as the track's `trajectory.manoeuvres`, with latitude and longitude at both
    ends), `warnings.csv` (every track's reconstruction warnings; `summary.json` counts them),
    `sensors.json`, `sensors.png`,
    `problems.txt`, `summary.json`, `map.png`, or all of them as `results.zip`."""
    runner = _runner(request)
    if name not in RESULT_FILES:
        raise HTTPException(404, f"no result file {shortened(name)!r} (files: "
                            f"{', '.join(RESULT_FILES)})")
    _finished(runner, job_id)
    path = runner.result_file(job_id, name)
    if path is None:
        why = {"filters.parquet": "it asked for no filters, or none could run on its tracks",
               "samples.parquet": "it asked for no samples (`sample_step_s`), or no track "
               "kept any"}.get(name, "no track was reconstructed")
        raise HTTPException(404, f"job {job_id} has no {name} ({why})")
    return _file(path, _MEDIA.get(Path(name).suffix, "application/octet-stream"), name)

