"""The HTML pages of the reports: a :class:`Document` assembled part by part, rendered as one
self-contained page (inline CSS, the plots embedded as base64), and :func:`write_folder`, which writes
it with its PNGs atomically.

Nothing here knows a calibration: the pages' calibration parts are in :mod:`eyetohand.reports.sections`.
Every text given to a :class:`Document` is escaped, except the fragments passed to :meth:`Document.add`.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import os
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from eyetohand._version import __version__
from eyetohand.core import InputError, atomic_write_bytes, atomic_write_text

__all__ = ["CSS", "PNG_NAMES", "Document", "escape", "mm", "write_folder"]

#: every plot a report of this package writes: rewriting a folder drops those the new report lacks
PNG_NAMES = (
    "convergence.png",
    "check_errors.png",
    "train_errors.png",
    "residual_vectors.png",
    "point_errors.png",
)


def escape(text) -> str:
    """``str(text)`` escaped for HTML text and attribute values (quotes too)."""
    return html.escape(str(text), quote=True)


def mm(value, digits: int = 4) -> str:
    """A millimetre value as the tables print it (4 decimals: 0.1 µm); '—' for a missing value."""
    if value is None:
        return "—"
    v = float(value)
    if not np.isfinite(v):
        return "—"
    text = f"{v:.{digits}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # no "-0.0000"


#: cells that do not count against a numeric column: missing or unreadable values
_PLACEHOLDERS = ("", "—", "n/a", "illegible")


def _is_numeric(cell: str) -> bool:
    """True for a formatted number such as '0.0269', '-3', '+12 %', '16'."""
    text = str(cell).strip().removesuffix("%").strip()
    try:
        float(text)
    except ValueError:
        return False
    return True


def _png(ax) -> bytes:
    """The figure of ``ax`` as PNG bytes (rendered in memory)."""
    buf = io.BytesIO()
    ax.figure.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


class Document:
    """An HTML document being assembled, with the PNGs it embeds (``files``: name → bytes)."""

    def __init__(self, title: str):
        self.title = title
        self.parts: list[str] = []
        self.files: dict[str, bytes] = {}

    def add(self, fragment: str) -> None:
        """Append an HTML fragment as it is (not escaped)."""
        self.parts.append(fragment)

    def h2(self, text: str, anchor: str) -> None:
        """A section heading, the target of ``#anchor``."""
        self.add(f'<h2 id="{escape(anchor)}">{escape(text)}</h2>')

    def h3(self, text: str) -> None:
        """A sub-heading."""
        self.add(f"<h3>{escape(text)}</h3>")

    def p(self, text: str, cls: str = "") -> None:
        """A paragraph, of CSS class ``cls`` when given ('muted', 'warn')."""
        c = f' class="{cls}"' if cls else ""
        self.add(f"<p{c}>{escape(text)}</p>")

    @contextmanager
    def details(self, summary: str) -> Iterator[None]:
        """What is added inside the ``with`` goes in a collapsed ``<details>`` headed by ``summary``."""
        self.add(f"<details><summary>{escape(summary)}</summary>")
        yield
        self.add("</details>")

    def cards(self, items: Iterable[tuple[str, str, str]]) -> None:
        """A row of key figures, each ``(label, value, unit)``."""
        parts = ['<div class="cards">']
        for k, v, u in items:
            parts.append(
                f'<div class="card"><div class="k">{escape(k)}</div><div class="v">{escape(v)}'
                f'<span class="u">{escape(u)}</span></div></div>'
            )
        parts.append("</div>")
        self.add("".join(parts))

    def notes(self, notes: list[str], warn: bool = False) -> None:
        """A bulleted list of notes (in the warning colour with ``warn``); 'none' when there are none."""
        if not notes:
            self.p("none", "muted")
            return
        cls = ' class="warn"' if warn else ""
        self.add('<ul class="notes">' + "".join(f"<li{cls}>{escape(n)}</li>" for n in notes) + "</ul>")

    def figure(self, name: str, ax, caption: str) -> None:
        """The figure of ``ax`` embedded as a PNG with its caption; kept in ``files`` as ``name``."""
        data = _png(ax)
        self.files[name] = data
        b64 = base64.b64encode(data).decode("ascii")
        self.add(
            f'<figure><img src="data:image/png;base64,{b64}" alt="{escape(caption)}">'
            f'<figcaption>{escape(caption)} <span class="muted">(also saved as {escape(name)})</span>'
            "</figcaption></figure>"
        )

    def table(
        self, header: list[str] | None, rows: list[list[str]], *, row_classes: list[str] | None = None
    ) -> None:
        """A table of already formatted cells. Numeric cells (and their columns' headers) are right
        aligned in tabular figures; ``header=None`` gives a key–value table without a header row."""
        ncol = max([len(header or [])] + [len(r) for r in rows])
        numeric_col = [
            all(_is_numeric(r[i]) for r in rows if i < len(r) and r[i] not in _PLACEHOLDERS)
            and any(i < len(r) and r[i] not in _PLACEHOLDERS for r in rows)
            for i in range(ncol)
        ]
        out = ['<div class="scroll"><table>']
        if header:
            out.append("<thead><tr>")
            for i, h in enumerate(header):
                out.append(f'<th class="{"num" if numeric_col[i] else ""}">{escape(h)}</th>')
            out.append("</tr></thead>")
        out.append("<tbody>")
        for r_i, row in enumerate(rows):
            rc = row_classes[r_i] if row_classes else ""
            out.append(f'<tr class="{rc}">' if rc else "<tr>")
            for i, cell in enumerate(row):
                cls = "num" if numeric_col[i] else ("key" if header is None and i == 0 else "")
                out.append(f'<td class="{cls}">{escape(cell)}</td>' if cls else f"<td>{escape(cell)}</td>")
            out.append("</tr>")
        out.append("</tbody></table></div>")
        self.add("".join(out))

    def render(self, subtitle: str = "") -> str:
        """The whole page: head, inline CSS, the title, ``subtitle`` and the generation time, the parts."""
        now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="generator" content="eyetohand {escape(__version__)}">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{escape(self.title)}</title><style>{CSS}</style></head><body><main>"
            f'<header><h1>{escape(self.title)}</h1><p class="muted">{escape(subtitle)}'
            f"{' · ' if subtitle else ''}generated {escape(now)} by eyetohand {escape(__version__)} · "
            "units: robot mm, image px</p></header>\n" + "\n".join(self.parts) + "\n</main></body></html>\n"
        )


CSS = """
:root { --fg:#1b1f24; --muted:#5b6570; --line:#d6dbe1; --zebra:#f5f7f9; --accent:#0072B2; --warn:#b35900; }
* { box-sizing: border-box; }
body { margin:0; color:var(--fg); background:#fff;
  font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1080px; margin: 0 auto; padding: 24px 28px 60px; }
header { border-bottom: 2px solid var(--accent); margin-bottom: 18px; }
h1 { font-size: 22px; margin: 0 0 4px; }
h2 { font-size: 17px; margin: 30px 0 8px; padding-bottom: 3px; border-bottom: 1px solid var(--line); }
h3 { font-size: 14.5px; margin: 18px 0 6px; }
p { margin: 6px 0; }
.muted { color: var(--muted); font-size: 12.5px; }
.warn { color: var(--warn); }
.cards { display: flex; flex-wrap: wrap; gap: 12px; margin: 10px 0 4px; }
.card { border: 1px solid var(--line); border-radius: 6px; padding: 8px 14px; min-width: 150px; }
.card .k { color: var(--muted); font-size: 12px; }
.card .v { font-size: 20px; font-weight: 600; font-variant-numeric: tabular-nums; }
.card .u { font-size: 12px; color: var(--muted); margin-left: 3px; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 13px; }
th, td { padding: 3px 10px; border-bottom: 1px solid var(--line); text-align: left; vertical-align: top; }
th { background: #eef1f4; font-weight: 600; vertical-align: bottom; }
th.num { text-align: right; }
td.num { text-align: right; font-variant-numeric: tabular-nums;
  font-family: ui-monospace, "SFMono-Regular", Menlo, Consolas, monospace; }
.scroll { overflow-x: auto; max-width: 100%; }
tbody tr:nth-child(even) { background: var(--zebra); }
td.key { color: var(--muted); white-space: nowrap; padding-right: 18px; }
tr.outlier td { background: #fff1e0; }
tr.summary td { font-weight: 600; border-top: 2px solid var(--line); }
figure { margin: 12px 0 18px; }
figure img { max-width: 100%; height: auto; border: 1px solid var(--line); }
figcaption { font-size: 12.5px; color: var(--muted); margin-top: 3px; }
ul.notes { margin: 4px 0; padding-left: 20px; }
pre { background: var(--zebra); padding: 6px 8px; overflow-x: auto; font-size: 12px; margin: 2px 0; }
details { margin: 8px 0; }
summary { cursor: pointer; font-weight: 600; }
nav a { margin-right: 12px; font-size: 13px; }
@media print { details { display: block; } main { padding: 0; } }
"""


def write_folder(
    out_dir: str | os.PathLike, html_text: str, files: Mapping[str, bytes], stale: Iterable[str] = PNG_NAMES
) -> Path:
    """Write ``files`` (the PNGs), then ``index.html``, each atomically, into ``out_dir`` (made if
    missing); then drop the files named in ``stale`` that this page does not have (an earlier run's
    plots). Returns the path of ``index.html``; :class:`InputError` when the folder cannot be written."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            atomic_write_bytes(out / name, data)
        index = atomic_write_text(out / "index.html", html_text)
        for name in stale:
            if name not in files and (out / name).is_file():
                (out / name).unlink()
    except OSError as exc:
        raise InputError(f"{out}: cannot write the report ({exc.strerror or exc})") from None
    return index
