"""The app's refusal without HTTP: an :class:`ApiError` carries the status, the words and the field."""

from __future__ import annotations

from eyetohand.core import InputError


class ApiError(Exception):
    """An error answered as ``{"error": message, "field": field}`` with ``status``."""

    def __init__(self, status: int, message: str, field: str | None = None, line: int | None = None):
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field
        self.line = line

    def to_dict(self) -> dict:
        """The JSON body's fields (``status`` too, for a job's ``error``)."""
        return {"status": self.status, "error": self.message, "field": self.field, "line": self.line}


def input_error(exc: InputError, default_field: str | None = None, status: int = 422) -> ApiError:
    """An InputError from the library as an ApiError: its one-line message, the request field it
    names (``pairs[3].u``, from the error's ``index``/``field``), else ``default_field``, and the
    line of a text it names."""
    return ApiError(status, str(exc), exc.field_path or default_field, exc.line)
