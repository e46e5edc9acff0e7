"""The two exceptions that mean "your input is wrong" (the CLI turns both into exit code 2).

An :class:`InputError` carries where the problem is as attributes, so that every interface can say it
in its own form from the same facts: the CLI prints ``str(exc)`` (one line), the HTTP service builds
its 4xx body from ``field_path`` and ``line``, the TCP service answers ``ERR <reason>``.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: a file, line or field that is not what was expected.

    ``InputError(reason, source=..., line=..., index=..., field=...)``; ``str(exc)`` is one line that
    names where the problem is, e.g. ``pairs.csv line 4, field 'u': 'abc' is not a number`` or
    ``request pairs[3], field 'u': True is not a number``. Called with the message alone, the message
    is taken as already saying where.

    Attributes: ``reason`` (the message without the location), ``source`` (file or request part),
    ``line`` (1-based line of a text file), ``index`` (0-based entry of a list of records, named
    ``label``: ``pairs[3]``), ``field`` (a column or key).
    """

    def __init__(
        self,
        reason: str,
        *,
        source: str | None = None,
        line: int | None = None,
        index: int | None = None,
        field: str | None = None,
        label: str = "pairs",
    ) -> None:
        self.reason = str(reason)
        self.source = source
        self.line = line
        self.index = index
        self.field = field
        self.label = label
        super().__init__(self._format())

    @property
    def where(self) -> str:
        """The location part of the message ('' when the error carries none)."""
        head = self.source or ""
        if self.line is not None:
            head += f" line {self.line}"
        if self.index is not None:
            head += f" {self.label}[{self.index}]"
        head = head.strip()
        if self.field is not None:
            head = f"{head}, field '{self.field}'" if head else f"field '{self.field}'"
        return head

    @property
    def field_path(self) -> str | None:
        """The entry and key as a request path, ``pairs[3].u``; None when the error names neither."""
        if self.index is None:
            return self.field
        path = f"{self.label}[{self.index}]"
        return f"{path}.{self.field}" if self.field else path

    def _format(self) -> str:
        where = self.where
        return f"{where}: {self.reason}" if where else self.reason

    def with_source(self, source: str) -> InputError:
        """The same error located in ``source`` (when it names no source yet): for errors raised on
        arrays and re-raised by a caller that knows which file or request they came from."""
        if self.source is not None or not source:
            return self
        err = type(self)(
            self.reason, source=source, line=self.line, index=self.index, field=self.field, label=self.label
        )
        return err

    def __reduce__(self):  # picklable across process pools with its attributes
        return (
            _rebuild,
            (type(self), self.reason, self.source, self.line, self.index, self.field, self.label),
        )


def _rebuild(cls, reason, source, line, index, field, label):
    return cls(reason, source=source, line=line, index=index, field=field, label=label)


class DegenerateError(InputError):
    """Geometry that cannot determine the model: too few points, collinear or coplanar points."""
