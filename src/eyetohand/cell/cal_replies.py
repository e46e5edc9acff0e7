"""How the CAL collection (:class:`eyetohand.cell.collect.Collector`) words its replies: ``plain``
(``OK [fields]``, ``OK DONE``, ``ERR <reason>``) or ``ur`` (four numbers for URScript's
``socket_read_ascii_float(4)``, written by the one ur formatter of :mod:`eyetohand.cell.replies`);
the collection's module docstring has the protocol."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from eyetohand.cell.line import UR_ERROR_CODES, CommandError, ascii_reason
from eyetohand.cell.replies import UR_COUNTS, ur_line, ur_number

UR_STATES = {"none": 0, "collecting": 1, "calibrated": 2, "aborted": 3}


class ReplyFormat(Protocol):
    """How a :class:`Collector` words its replies (one line each, no line end)."""

    name: str

    def ok(self, command: str, fields: Sequence[str], planned: int) -> str:
        """A command done: ``command`` the CAL word (``POINT``, ``STATUS``, ...), ``fields`` its reply
        fields as the plain format sends them, ``planned`` the open collection's planned poses."""
        ...

    def done(self) -> str:
        """``CAL NEXT`` with every planned pose recorded or failed."""
        ...

    def error(self, exc: CommandError) -> str:
        """A command refused."""
        ...


class PlainReplies:
    """``OK [fields]``, ``OK DONE`` and ``ERR <reason>`` (the reason in ASCII: :func:`ascii_reason`)."""

    name = "plain"

    def ok(self, command: str, fields: Sequence[str], planned: int) -> str:
        return "OK" + (" " + ",".join(fields) if fields else "")

    def done(self) -> str:
        return "OK DONE"

    def error(self, exc: CommandError) -> str:
        return f"ERR {ascii_reason(str(exc))}"


class URReplies:
    """Four numbers ``(status,a,b,c)`` for URScript's ``socket_read_ascii_float(4)`` (module docstring):
    status 1 and the fields for OK, 0 for DONE, the refusal's :data:`UR_ERROR_CODES` number for ERR."""

    name = "ur"

    def ok(self, command: str, fields: Sequence[str], planned: int) -> str:
        if command == "END":  # the model's name is not a number: it is in the journal
            nums = [float(f) for f in fields[1:]]
        elif command == "STATUS":  # name,n,state -> n,state number,planned poses
            nums = [float(fields[1]), UR_STATES[fields[2]], planned]
        elif command == "PLATE":  # points,A,B,C,D -> points, corners to touch (labels are not numbers)
            nums = [float(fields[0]), len(fields) - 1]
        else:
            nums = [float(f) for f in fields]
        return self._line([1, *nums])

    def done(self) -> str:
        return self._line([0])

    def error(self, exc: CommandError) -> str:
        return self._line([UR_ERROR_CODES[exc.code]])

    @staticmethod
    def _line(nums: list[float]) -> str:
        """``(status,a,b,c)``: the ur format's one formatter (:func:`eyetohand.cell.replies.ur_line`)."""
        return ur_line(int(nums[0]), [ur_number(v) for v in nums[1:]], UR_COUNTS["CAL"])


#: the reply formats by name (``Collector(reply_format=...)``, ``serve --reply-format``)
REPLY_FORMATS: dict[str, type[ReplyFormat]] = {"plain": PlainReplies, "ur": URReplies}


__all__ = ["REPLY_FORMATS", "UR_STATES", "PlainReplies", "ReplyFormat", "URReplies"]
