"""Errors that a user can read: each names the file and the field at fault."""

from __future__ import annotations

from pathlib import Path


class ElastoidError(Exception):
    """Base of every error ElastoID reports to a user instead of a traceback."""


class ExperimentError(ElastoidError):
    """Malformed experiment input.

    ``file`` is the offending file, ``field`` the TOML key, CSV column or image
    property at fault (dotted, e.g. ``specimen.regions[1].radius_mm``).
    """

    def __init__(self, file: str | Path, field: str, message: str):
        self.file = str(file)
        self.field = field
        self.message = message
        where = f"{self.file}: {field}" if field else self.file
        super().__init__(f"{where}: {message}")


class Cancelled(ElastoidError):
    """A long computation was stopped by its cancel event."""


class MeshingError(ElastoidError):
    """The mesher failed or produced an unusable mesh."""
