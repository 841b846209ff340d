"""Every test module gets a job store of its own (``TRAJRECON_DATA_DIR``, inherited by the
servers it starts): no test reads or resumes the jobs of another, or of the user's own
data directory."""

from __future__ import annotations

import os

import pytest


@pytest.fixture(autouse=True, scope="module")
def _job_data_dir(tmp_path_factory: pytest.TempPathFactory):
    before = os.environ.get("TRAJRECON_DATA_DIR")
    os.environ["TRAJRECON_DATA_DIR"] = str(tmp_path_factory.mktemp("job-data"))
    yield
    if before is None:
        os.environ.pop("TRAJRECON_DATA_DIR", None)
    else:
        os.environ["TRAJRECON_DATA_DIR"] = before
