"""HTTP service over ``solver``: ``service.app:app`` (FastAPI); ``python -m service`` runs it."""

__version__ = "1.0.0"
