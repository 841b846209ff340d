"""HTTP service over ``solver``: ``service.app:app`` (FastAPI); ``python -m service`` runs it."""

from importlib.metadata import PackageNotFoundError, version

try:  # one source: the version in pyproject.toml, as installed
    __version__ = version("radar-trajrecon")
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"
