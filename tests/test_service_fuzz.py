"""A fuzz run of the whole API against a real server (``python -m service``): schemathesis
generates valid and invalid requests for every operation of the app's OpenAPI document, and
hypothesis sends raw bodies that are not JSON or not the schema's shape. No answer may be a
5xx; every answer is as documented (status, content type, headers, schema), every error
answer the ``ErrorResponse``.

Bounded: 200 generated requests and 100 raw bodies to ``POST /v1/reconstructions``, 15 to each
other operation; one worker, no warm-up, at most 60 plots per request and a 10-s solve limit."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from procs import start_service, stop
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from service.app import create_app
from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
SEED_BATCH = json.loads((ROOT / "examples" / "seed_track.json").read_text())

schema = schemathesis.openapi.from_dict(create_app(Settings()).openapi())


@pytest.fixture(scope="module")
def server():
    proc, url = start_service({
        "TRAJRECON_WORKERS": "1", "TRAJRECON_WARMUP": "false", "TRAJRECON_LOG_LEVEL": "WARNING",
        "TRAJRECON_ACCESS_LOG": "false", "TRAJRECON_MAX_PLOTS": "60",
        "TRAJRECON_SOLVE_TIME_LIMIT_S": "10", "TRAJRECON_MAX_QUEUED_SOLVES": "64",
        # room for every job the run's valid bodies create: the limit's 503 (documented, and
        # tested in test_service_jobs) is not the server error this run looks for
        "TRAJRECON_JOBS_MAX_QUEUED": "500"})
    try:
        yield url
    finally:
        stop(proc)


def is_error_body(r: httpx.Response) -> bool:
    try:
        body = r.json()
    except ValueError:
        return False
    return isinstance(body, dict) and isinstance(body.get("message"), str) and isinstance(
        body.get("detail"), list)


def check(case, server: str) -> None:
    response = case.call(base_url=server, timeout=60)
    case.validate_response(response, checks=[
        not_a_server_error, status_code_conformance, content_type_conformance,
        response_headers_conformance, response_schema_conformance])
    if response.status_code >= 400 and response.status_code != 405:
        assert is_error_body(response), response.text[:300]


@schema.include(method="POST", path="/v1/reconstructions").parametrize()
@settings(max_examples=200, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_reconstructions_never_answer_5xx(case, server):
    check(case, server)


@schema.exclude(method="POST", path="/v1/reconstructions").parametrize()
@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_no_other_operation_answers_5xx(case, server):
    check(case, server)


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=4),
    max_leaves=12)
_near = st.fixed_dictionaries({
    "radar": st.fixed_dictionaries({}, optional={"range_error_m": _json,
                                                 "azimuth_error_deg": _json}),
    "plots": st.lists(st.fixed_dictionaries({}, optional={
        "t": _json, "range_m": _json, "azimuth_deg": _json}), max_size=5),
}, optional={"bounds": _json, "window": _json, "method": _json, "filters": _json})


@settings(max_examples=100, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(body=st.binary(max_size=200) | _json.map(lambda v: json.dumps(v).encode())
       | _near.map(lambda v: json.dumps(v).encode()))
def test_raw_bodies_never_give_5xx(server, body):
    r = httpx.post(server + "/v1/reconstructions", content=body, timeout=60,
                   headers={"content-type": "application/json"})
    assert r.status_code < 500, r.text[:300]
    assert r.status_code == 200 or (r.status_code in (400, 413, 422) and is_error_body(r))
