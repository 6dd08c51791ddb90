"""The REST API (``/api/...``, OpenAPI at ``/docs``) and the landing page: see :func:`create_app`."""

from lab.api.app import create_app

__all__ = ["create_app"]
