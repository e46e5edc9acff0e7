"""CSV text as spreadsheets save it: the separator and the decimal mark, found from the file itself.

Excel in a German or French locale saves "CSV" with ``;`` between fields and a decimal comma
(``441,615``), often with a UTF-8 BOM (dropped when the bytes are decoded), CR LF line ends and a
trailing ``;``. Every loader of numbers (pairs, check pairs, image points, poses, conveyor sessions)
reads its text through :func:`read_csv`, so one set of rules and words serves them all:

**Separator.** The candidates are ``,``, ``;`` and tab, those that occur in the header (the first
non-blank line); a header with one of them is split on it. With several, the one that splits the
header into two or more columns *and every data row into as many* is taken; when two do, the file is
refused (re-save it with one separator). When none does, the one that gives the header the most
columns is taken and the loader names the first row whose count differs. One trailing empty field
more or less than the header (a trailing ``;`` on some lines) is not a difference.

**Decimal mark.** A field that is a number with one comma (``441,615``, ``-0,5``, ``1,5E-03``) is a
decimal comma when the file has no number with a decimal point; it is then read as the same digits
with a point, so the floats are bit-identical to the file written with ``.``. Refused, never
guessed: numbers with decimal commas and numbers with decimal points in one file; a file whose every
comma is followed by exactly three digits (``1,500``: a thousands separator or a decimal comma?);
and, in a comma-separated file, a row with more fields than the header (unquoted decimal commas).
The loader records a note of what it assumed (``read as ';'-separated with decimal commas``).
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass

from eyetohand.core.errors import InputError

SEPARATORS = {",": "','", ";": "';'", "\t": "tab"}
"""The field separators read, and how messages name them."""

_COMMA_NUMBER = re.compile(r"\s*[+-]?(\d+,\d*|,\d+)([eE][+-]?\d+)?\s*\Z")
_POINT_NUMBER = re.compile(r"\s*[+-]?(\d+\.\d*|\.\d+)([eE][+-]?\d+)?\s*\Z")
_THOUSANDS = re.compile(r"\s*[+-]?\d{1,3}(,\d{3})+\s*\Z")

RESAVE = "re-save it with ',' between fields and '.' as the decimal point (or ';' and decimal commas)"


@dataclass(frozen=True)
class CsvTable:
    """The rows of a CSV text (decimal commas already turned into points), the index of the header
    row (the first non-blank line), the separator, the decimal mark and the note saying what was
    assumed (None for the default: ``,`` and ``.``)."""

    rows: list[list[str]]
    first: int
    separator: str
    decimal_comma: bool
    note: str | None


def read_csv(text: str, name: str) -> CsvTable:
    """The table of a CSV text with its dialect found (module docstring); errors name ``name``, the
    line and, where there is one, the field."""
    lines = text.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise InputError(f"{name}: empty file, expected a header line 'u,v,x,y[,z][,id]' and rows")
    header_line = lines[first]
    candidates = [s for s in SEPARATORS if s in header_line]
    if not candidates:
        if "|" in header_line:
            raise InputError(
                "columns separated by '|', expected ',', ';' or tab", source=name, line=first + 1
            )
        candidates = [","]
    tables = {s: _split(lines, first, s, name) for s in candidates}
    sep = _separator(tables, first, name)
    rows = tables[sep]
    if sep == ",":
        _refuse_split_decimals(rows, first, name)
    decimal_comma = False
    if sep != "," or '"' in text:  # a comma inside a field of a comma-separated file is quoted
        decimal_comma = _decimal_comma(rows, first, name)
    if decimal_comma:
        rows = [
            row if k <= first else [c.replace(",", ".") if _COMMA_NUMBER.match(c) else c for c in row]
            for k, row in enumerate(rows)
        ]
    return CsvTable(rows, first, sep, decimal_comma, _note(name, sep, decimal_comma))


def _split(lines: list[str], first: int, sep: str, name: str) -> list[list[str]]:
    try:
        rows = list(csv.reader(lines, delimiter=sep))
    except csv.Error as exc:
        raise InputError(f"{name}: not a readable CSV file ({exc})") from None
    n = len(rows[first])
    trailing_empty = n > 1 and not rows[first][-1].strip()
    for k in range(first + 1, len(rows)):
        row = rows[k]
        if len(row) == n + 1 and not row[-1].strip():
            rows[k] = row[:-1]  # a trailing separator the header lacks
        elif trailing_empty and len(row) == n - 1 and row:
            rows[k] = [*row, ""]  # the header's trailing separator, missing on this line
    return rows


def _consistent(rows: list[list[str]], first: int) -> bool:
    n = len(rows[first])
    return n >= 2 and all(len(r) == n for r in rows[first + 1 :] if r and any(c.strip() for c in r))


def _separator(tables: dict[str, list[list[str]]], first: int, name: str) -> str:
    if len(tables) == 1:
        return next(iter(tables))
    fits = [s for s, rows in tables.items() if _consistent(rows, first)]
    if len(fits) == 1:
        return fits[0]
    if len(fits) > 1:
        both = " and ".join(SEPARATORS[s] for s in fits)
        raise InputError(
            f"the header and every row split into columns on {both} alike: which separates the "
            "fields? Re-save the file with one separator",
            source=name,
            line=first + 1,
        )
    return max(tables, key=lambda s: len(tables[s][first]))  # ties: the order of SEPARATORS


def _refuse_split_decimals(rows: list[list[str]], first: int, name: str) -> None:
    """In a comma-separated file, a row of more fields than the header whose fields are all whole
    numbers is most likely numbers with unquoted decimal commas ('1,5,2,5' for 1.5 and 2.5)."""
    n = len(rows[first])
    for k in range(first + 1, len(rows)):
        row = rows[k]
        if len(row) > n and all(c.strip().lstrip("+-").isdigit() for c in row if c.strip()):
            raise InputError(
                f"{len(row)} fields, the header has {n}: numbers with decimal commas in a file whose "
                f"fields are separated by commas cannot be told apart; {RESAVE}",
                source=name,
                line=k + 1,
            )


def _decimal_comma(rows: list[list[str]], first: int, name: str) -> bool:
    """Whether the numbers have decimal commas (module docstring); refuses a mixed or an ambiguous file."""
    header = [h.strip() for h in rows[first]]
    comma_at = point_at = None
    decided = False  # a comma field that cannot be a thousands separator
    for k in range(first + 1, len(rows)):
        for j, c in enumerate(rows[k]):
            if "," in c and _COMMA_NUMBER.match(c):
                if comma_at is None:
                    comma_at = (k, j, c)
                if not decided and not _THOUSANDS.match(c):
                    decided = True
            elif point_at is None and "." in c and _POINT_NUMBER.match(c):
                point_at = (k, j, c)
        if comma_at is not None and point_at is not None:
            break
    if comma_at is None:
        return False

    def field(j: int) -> str | None:
        return header[j] if j < len(header) and header[j] else None

    if point_at is not None:
        k, j, c = point_at
        k0, j0, c0 = comma_at
        raise InputError(
            f"{c.strip()!r} has a decimal point, but line {k0 + 1}"
            f"{f' ({field(j0)})' if field(j0) else ''} has {c0.strip()!r}, a decimal comma: one file, "
            "one decimal mark; re-save it with one",
            source=name,
            line=k + 1,
            field=field(j),
        )
    if not decided:
        k, j, c = comma_at
        raise InputError(
            f"{c.strip()!r}: a decimal comma or a thousands separator? Every comma in this file has three "
            "digits after it; re-save it with '.' as the decimal point and no thousands separators",
            source=name,
            line=k + 1,
            field=field(j),
        )
    return True


def _note(name: str, sep: str, decimal_comma: bool) -> str | None:
    if sep == "," and not decimal_comma:
        return None
    how = "tab-separated" if sep == "\t" else f"{SEPARATORS[sep]}-separated"
    if decimal_comma:
        how += " with decimal commas"
        if sep == ";":
            how += " (German/French Excel)"
        elif sep == ",":
            how += " in quoted fields"
    return f"{name}: read as {how}"
