"""The robot programs of examples/robots/ against the real server process, byte for byte.

No controller runs here, so each program's exchange is replayed: the bytes its send primitive puts
on the wire (line ends / end strings included) go to ``eyetohand serve`` (``sim:`` camera), and the
replies are read back with the controller's documented rules, emulated by one small function each
below (the manual's rule in its docstring). What each program sends — the BEGIN line, the port,
the line end, the number format — is read out of the program's own text, so a program that drifts
fails here. The plan is cut from grid:5x5 to grid:3x3 (the same exchange, shorter).

The token: every program's first line is ``AUTH <token>`` with the token written at its top
(:func:`program_auth` reads the token, the bytes and the program's own test of the reply out of its
text); the replays run against a server started with ``--token`` that token, and every program is
shown stopping on a wrong token (code -14) and talking to a server without a token.

Also: robot_client.py's documented ``--rect -40,...`` form and a clean Ctrl-C.
"""

from __future__ import annotations

import math
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import pytest
from helpers import ROBOTS, ServeProcess, src_env

SEED = 5
PLAN = "grid:3x3"
# The programs' rectangle (0,570)-(70,650) at z 150 lies inside this cell's view: all 9 poses are
# recorded. The skip path (the server's real "ERR outside the image: ..." reply, longer than RAPID's
# 80 characters) is taken by test_abb_rapid_skips_a_pose_outside_the_view with the old rectangle.
N_RECORDED, N_SKIPPED = 9, 0
OUTSIDE_RECT = "-40,570,60,650"  # its corner (-40,650) is cut by the image border here


def serve(tmp_path: Path, cell_file: Path, *extra: str) -> ServeProcess:
    return ServeProcess(
        tmp_path / "data", "--camera", f"sim:{cell_file}?seed={SEED}", "--calibration", "cell1", *extra
    )


def program(rel: str) -> str:
    return (ROBOTS / rel).read_text()


def one(pattern: str, text: str, flags: int = 0) -> re.Match:
    """The single match of ``pattern`` in a program's text (the test's hold on what the program does)."""
    found = list(re.finditer(pattern, text, flags))
    assert len(found) == 1, f"expected one match of {pattern!r}, found {len(found)}"
    return found[0]


def code(text: str, comment: str) -> str:
    """A program's text without its comments (``comment`` to the end of a line; no string here holds it)."""
    return "\n".join(line.split(comment, 1)[0] for line in text.splitlines())


def short_plan(begin: str) -> str:
    assert ",grid:5x5," in begin, begin
    return begin.replace(",grid:5x5,", f",{PLAN},")


class Wire:
    """The TCP connection as the controller sees it: bytes out, a byte stream in; ``sent`` keeps
    every send, exactly as it went on the wire."""

    def __init__(self, port: int, timeout_s: float = 60.0):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        self.buf = b""
        self.sent: list[bytes] = []

    def send(self, data: bytes) -> None:
        self.sent.append(data)
        self.sock.sendall(data)

    def read_until(self, end: bytes) -> bytes:
        """Everything up to and including the first ``end``."""
        while end not in self.buf:
            chunk = self.sock.recv(4096)
            assert chunk, "the server closed the connection"
            self.buf += chunk
        i = self.buf.index(end) + len(end)
        out, self.buf = self.buf[:i], self.buf[i:]
        return out

    def read_byte(self) -> bytes:
        if not self.buf:
            chunk = self.sock.recv(4096)
            assert chunk, "the server closed the connection"
            self.buf += chunk
        out, self.buf = self.buf[:1], self.buf[1:]
        return out

    def close(self) -> None:
        self.sock.close()


# ---- the controllers' documented rules -------------------------------------------------------------

NUM_LITERAL = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"


def ur_socket_read_ascii_float(wire: Wire, n: int) -> list[float]:
    """URScript Manual, "Interfaces", socket_read_ascii_float(number, socket_name, timeout): reads
    ``number`` floats sent as ASCII in brackets, ``(1.414, 3.14159, 1.616, 0.0)``; returns
    ``[number, v1, ..., vn]``, or ``[0, nan, ...]`` when it cannot read exactly that many. Anything
    before the ``(`` (the previous reply's line end) is skipped."""
    text = wire.read_until(b")").decode("ascii")
    inner = text[text.index("(") + 1 : -1] if "(" in text else ""
    fields = [f.strip() for f in inner.split(",")]
    if len(fields) != n or not all(re.fullmatch(NUM_LITERAL, f) for f in fields):
        return [0.0] + [math.nan] * n
    return [float(n)] + [float(f) for f in fields]


def ur_str_of_float(v: float) -> str:
    """URScript str_cat/to_str of a float: about 6 significant digits (as the script's header
    assumes; the server reads any decimal form)."""
    return f"{v:.6g}"


def rapid_string(s: str) -> str:
    """RAPID data type string: at most 80 characters; a longer one (e.g. from "+") is a run-time
    error, ERR_STRTOOLONG."""
    assert len(s) <= 80, f"RAPID ERR_STRTOOLONG: {len(s)} characters: {s!r}"
    return s


def rapid_strtoval(s: str) -> float | None:
    """RAPID StrToVal(Str, Val): TRUE and the value when Str is a num literal (integer, decimal or
    exponential form), FALSE otherwise (here: None)."""
    return float(s) if re.fullmatch(NUM_LITERAL, s) else None


def rapid_numtostr(v: float, dec: int) -> str:
    """RAPID NumToStr(Val, Dec): Dec decimals, "." decimal point."""
    return f"{v:.{dec}f}"


def karel_cnv_str_real(s: str) -> float | None:
    """KAREL CNV_STR_REAL(source, target): target is the REAL that source spells, and is set
    UNINIT (here: None) when source is not a valid REAL."""
    return float(s) if re.fullmatch(r"\s*" + NUM_LITERAL + r"\s*", s) else None


def karel_cnv_real_str(v: float, length: int, num_digits: int) -> str:
    """KAREL CNV_REAL_STR(source, length, num_digits, target): num_digits decimals, right-aligned
    in at least ``length`` characters."""
    return f"{v:{length}.{num_digits}f}"


def eki_send(data: bytes, eos: bytes) -> bytes:
    """EthernetKRL, "Sending data", binary data record with end string sent directly as a string:
    the CHAR array up to its first NUL, followed by the configured end string (EOS)."""
    return data.split(b"\0", 1)[0] + eos


def eki_receive(wire: Wire, eos: bytes, size: int) -> str:
    """EthernetKRL RAW STREAM element: the received stream is cut at the end string (EOS) into
    records of at most Size bytes, stored FIFO; EKI_GetString hands out the oldest, here without
    its EOS."""
    rec = wire.read_until(eos)[: -len(eos)]
    assert len(rec) <= size, f"a reply of {len(rec)} bytes does not fit Size={size}"
    return rec.decode("ascii")


def krl_sread_reals(text: str, offset: int, fmt: str) -> list[float]:
    """KRL SREAD(string, state, offset, format, ...): CREAD's formats; %f reads a REAL; the state's
    HITS is the number of values read (the program checks HITS = 3)."""
    pattern = "".join(f"({NUM_LITERAL})" if p == "%f" else re.escape(p) for p in re.split(r"(%f)", fmt))
    m = re.match(pattern, text[offset:])
    return [float(v) for v in m.groups()] if m else []


def spel_line_input(wire: Wire, terminator: bytes) -> str:
    """SPEL+ Line Input #: one line up to the port's terminator (SetNet), without it."""
    return wire.read_until(terminator)[: -len(terminator)].decode("ascii")


def spel_fmtstr(v: float, fmt: str) -> str:
    """SPEL+ FmtStr$(number, format$): "0.0000" gives 4 decimals, "." decimal point."""
    decimals = len(fmt.split(".", 1)[1]) if "." in fmt else 0
    return f"{v:.{decimals}f}"


def spel_val(s: str) -> float:
    """SPEL+ Val(string$): the number at the start of the string, 0 when there is none."""
    m = re.match(r"\s*" + NUM_LITERAL, s)
    return float(m.group()) if m else 0.0


def rapid_read_line(wire: Wire) -> str:
    """EyetohandCollect.mod's ReadLine: SocketReceive \\ReadNoOfBytes:=1 up to LF, CR dropped, 80 kept."""
    line = ""
    while (ch := wire.read_byte()) != b"\n":
        if ch != b"\r" and len(line) < 80:
            line = rapid_string(line + ch.decode("ascii"))
    return line


def karel_read_line(wire: Wire, reply_len: int) -> str:
    """eth_cal.kl's read_line: byte by byte to LF, CR dropped, cut to the STRING's length."""
    return wire.read_until(b"\n")[:-1].replace(b"\r", b"").decode("ascii")[:reply_len]


# ---- the token: AUTH first, as each program sends it -------------------------------------------------

PROGRAMS = [
    "ur/eyetohand_collect.script",
    "ur/eyetohand_pick.script",
    "abb/EyetohandCollect.mod",
    "abb/EyetohandPick.mod",
    "fanuc/eth_cal.kl",
    "fanuc/eth_pick.kl",
    "kuka/eyetohand_collect.src",
    "kuka/eyetohand_pick.src",
    "epson/EyetohandCollect.prg",
    "epson/EyetohandPick.prg",
]


@dataclass
class Auth:
    """A program's AUTH exchange, read out of its text: its token, the sends that put the line on the
    wire, how it reads the reply and its own two tests of it (OK; the refused token)."""

    token: str
    sends: list[bytes]
    read: Callable[[Wire], object]
    ok: Callable[[object], bool]
    refused: Callable[[object], bool]
    ur: bool = False

    def exchange(self, wire: Wire) -> object:
        for data in self.sends:
            wire.send(data)
        return self.read(wire)


def first_before(text: str, auth_call: str, *others: str) -> None:
    """The program authenticates before any other command (``auth_call`` comes first in its code)."""
    at = text.index(auth_call)
    assert all(at < text.index(o) for o in others), (auth_call, others)


def program_auth(rel: str, cr_item: bytes = b"\r\n") -> Auth:
    """What ``rel`` sends as its first line and how it judges the reply (``cr_item``: the bytes taken
    for KAREL's CR item, which the manual leaves open)."""
    text = program(rel)
    kind = rel.split("/")[0]
    if kind == "ur":
        token = one(r'^\s*TOKEN = "([^"]+)"', text, re.M).group(1)
        if rel.endswith("collect.script"):
            body = one(r"def auth\(\):(.*?)\n  end\n", text, re.S).group(1)
            one(r'socket_send_string\(str_cat\("AUTH ", TOKEN\), "cam"\)', body)
            code_14 = int(one(r"r\[1\] == (-\d+):", body).group(1))
            first_before(text, "\n  auth()", "cmd(BEGIN)")
        else:
            body = one(r"def cmd\(line\):(.*?)\n  end", text, re.S).group(1)
            code_14 = int(
                one(r'r = cmd\(str_cat\("AUTH ", TOKEN\)\)[^\n]*\n\s*if r\[1\] == (-\d+):', text).group(1)
            )
            first_before(text, 'cmd(str_cat("AUTH ", TOKEN))', "cmd(LOCATE)")
        line_end = bytes(int(b) for b in re.findall(r'socket_send_byte\((\d+), "cam"\)', body))
        n = int(one(r'socket_read_ascii_float\((\d+), "cam"', body).group(1))
        return Auth(
            token,
            [f"AUTH {token}".encode(), *(bytes([b]) for b in line_end)],  # socket_send_string, _byte
            lambda w: ur_socket_read_ascii_float(w, n),
            lambda r: r[0] == n and r[1] == 1,  # type: ignore[index]
            lambda r: r[0] == n and r[1] == code_14,  # type: ignore[index]
            ur=True,
        )
    if kind == "abb":
        token = one(r'CONST string TOKEN := "([^"]+)";', text).group(1)
        first_before(
            text,
            'Command("AUTH " + TOKEN)',
            "Command(BEGIN_CMD)" if "Collect" in rel else "Command(LOCATE_CMD)",
        )
        escapes = one(r'SocketSend sock \\Str:=cmd \+ "((?:\\[0-9A-F]{2})+)";', text).group(1)
        line_end = bytes(int(h, 16) for h in re.findall(r"\\([0-9A-F]{2})", escapes)).decode("ascii")
        n, prefix = one(r'IF Clip\(reply, (\d+)\) = "([^"]+)" Stop\w+\("the vision PC refused', text).groups()
        return Auth(
            token,
            [rapid_string("AUTH " + token + line_end).encode("ascii")],  # SocketSend \Str
            rapid_read_line,
            lambda r: r[:2] == "OK",  # type: ignore[index]
            lambda r: r[: int(n)] == prefix,  # type: ignore[index]
        )
    if kind == "fanuc":
        token = one(r"^\s*TOKEN = '([^']+)'", text, re.M).group(1)
        first_before(
            text, "\n  authenticate\n", "send_cmd(BEGIN_CMD)" if "cal" in rel else "send_cmd(LOCATE_CMD)"
        )
        one(r"send_cmd\('AUTH ' \+ TOKEN\)", text)
        n, prefix = one(
            r"IF SUB_STR\(reply, 1, (\d+)\) = '([^']+)' THEN[^\n]*\n\s*stop_\w+\('the vision PC refused", text
        ).groups()
        reply_len = int(one(r"reply : STRING\[(\d+)\]", text).group(1))
        return Auth(
            token,
            [f"AUTH {token}".encode() + cr_item],  # WRITE sock (line, CR)
            lambda w: karel_read_line(w, reply_len),
            lambda r: r[:2] == "OK",  # type: ignore[index]
            lambda r: r[: int(n)] == prefix,  # type: ignore[index]
        )
    if kind == "kuka":
        xml = program("kuka/EyetohandCal.xml")
        elem = one(r'<RECEIVE>.*<ELEMENT Tag="Reply" Type="STREAM" EOS="([\d,]+)" Size="(\d+)"', xml, re.S)
        eos, size = bytes(int(b) for b in elem.group(1).split(",")), int(elem.group(2))
        token = one(r'StrCopy\(cmd\[\], "AUTH ([^"]+)"\)', text).group(1)
        first_before(
            text,
            'StrCopy(cmd[], "AUTH ',
            'StrCopy(cmd[], "CAL BEGIN' if "collect" in rel else 'StrCopy(cmd[], "LOCATE ',
        )
        prefix = one(
            r'StrFind\(1, reply\[\], "([^"]+)", #CASE_SENS\) == 1 THEN[^\n]*\n'
            r'\s*MsgNotify\("eyetohand: the vision PC refused',
            text,
        ).group(1)
        return Auth(
            token,
            [eki_send(f"AUTH {token}".encode().ljust(128, b"\0"), eos)],  # one EKI_Send
            lambda w: eki_receive(w, eos, size).rstrip("\r\n"),
            lambda r: r.startswith("OK"),  # type: ignore[attr-defined]
            lambda r: r.startswith(prefix),  # type: ignore[attr-defined]
        )
    assert kind == "epson", rel
    token = one(r'token\$ = "([^"]+)"', text).group(1)
    terminator = {"CR": b"\r", "LF": b"\n", "CRLF": b"\r\n"}[
        one(r'SetNet #201, "[\d.]+", \d+, (CRLF|CR|LF),', text).group(1)
    ]
    first_before(text, 'Cmd("AUTH " + token$)', 'Cmd("CAL BEGIN' if "Collect" in rel else 'Cmd("LOCATE ')
    prefix = one(r'If InStr\(gReply\$, "([^"]+)"\) = 1 Then gReply\$ = "the vision PC refused', text).group(1)
    return Auth(
        token,
        [f"AUTH {token}".encode() + terminator],  # Print #201
        lambda w: spel_line_input(w, terminator).rstrip("\r"),
        lambda r: r[:2] == "OK",  # type: ignore[index]
        lambda r: r.startswith(prefix),  # type: ignore[attr-defined]
    )


@pytest.fixture(scope="module")
def servers(tmp_path_factory, cell_file):
    """Four servers: with a token none of the programs has, and without one; plain and ur replies."""
    root = tmp_path_factory.mktemp("auth")
    out = {}
    try:
        for ur in (False, True):
            fmt = ("--reply-format", "ur") if ur else ()
            out[ur, "wrong"] = serve(root / f"w{ur}", cell_file, "--token", "not-the-program-token", *fmt)
            out[ur, None] = serve(root / f"n{ur}", cell_file, *fmt)
        yield out
    finally:
        for srv in out.values():
            srv.stop()


@pytest.mark.parametrize("rel", PROGRAMS)
def test_program_stops_on_a_wrong_token_and_talks_without_one(rel, servers):
    """A wrong token: the program's own test of the reply says "refused" (code -14 in ur, the AUTH
    refusal in plain) and the server closes; a server without a token answers the same AUTH with OK."""
    auth = program_auth(rel)
    assert len(auth.token) >= 8 and auth.token != "not-the-program-token"
    wire = Wire(servers[auth.ur, "wrong"].tcp_port, timeout_s=20)
    try:
        reply = auth.exchange(wire)
        assert auth.refused(reply) and not auth.ok(reply), reply
        rest = wire.buf  # (ur: the reply's line end after the ")" it reads to)
        while chunk := wire.sock.recv(100):  # the server closes: recv gives b"" (the 20 s timeout: no)
            rest += chunk
        assert rest.strip() == b"", rest
    finally:
        wire.close()
    wire = Wire(servers[auth.ur, None].tcp_port, timeout_s=20)
    try:
        reply = auth.exchange(wire)
        assert auth.ok(reply) and not auth.refused(reply), reply
    finally:
        wire.close()


# ---- the programs, replayed --------------------------------------------------------------------------


def test_ur_script(tmp_path, cell_file):
    """UR: socket_send_string sends no line end (the script sends bytes 13, 10 itself), replies in the
    ur format are read by socket_read_ascii_float(4) and must give its count 4 every time."""
    text = program("ur/eyetohand_collect.script")
    begin = short_plan(one(r'BEGIN = "(CAL BEGIN [^"]+)"', text).group(1))
    assert int(one(r"^\s*PORT = (\d+)", text, re.M).group(1)) == 5000
    cmd_def = one(r"def cmd\(line\):(.*?)\n  end", text, re.S).group(1)
    line_end = bytes(int(b) for b in re.findall(r'socket_send_byte\((\d+), "cam"\)', cmd_def))
    assert line_end == b"\r\n"
    n_read = int(one(r'socket_read_ascii_float\((\d+), "cam"', cmd_def).group(1))
    auth = program_auth("ur/eyetohand_collect.script")
    srv = serve(tmp_path, cell_file, "--reply-format", "ur", "--token", auth.token)
    wire = Wire(srv.tcp_port)
    try:
        assert auth.ok(r := auth.exchange(wire)), r

        def cmd(line: str) -> list[float]:
            wire.send(line.encode("ascii"))  # socket_send_string: no line end
            for b in line_end:
                wire.send(bytes([b]))  # socket_send_byte
            r = ur_socket_read_ascii_float(wire, n_read)
            assert r[0] == n_read, f"{line!r}: socket_read_ascii_float gave {r}"
            return r

        assert cmd(begin)[1] == 1
        recorded, skipped = 0, []
        while True:
            r = cmd("CAL NEXT")
            if r[1] == 0:
                break
            assert r[1] == 1
            xyz = ",".join(ur_str_of_float(v) for v in r[2:5])
            r = cmd("CAL POINT " + xyz)
            if r[1] == -4:  # moving: once more
                r = cmd("CAL POINT " + xyz)
            if r[1] != 1:
                skipped.append(r[1])
            else:
                recorded += 1
                assert r[2] == recorded
        r = cmd("CAL END")
        assert r[1] == 1 and r[2] == N_RECORDED and 0 < r[3] < 0.5, r
        assert skipped == []  # -5 would be: outside the image
        assert wire.sent[:6] == [f"AUTH {auth.token}".encode(), b"\r", b"\n", begin.encode(), b"\r", b"\n"]
    finally:
        wire.close()
        srv.stop()


def abb_run(wire: Wire, begin: str, line_end: bytes, dec: int) -> dict:
    """EyetohandCollect.mod's main loop on the wire (AUTH first), with RAPID's string rules."""
    messages: list[str] = []
    auth = program_auth("abb/EyetohandCollect.mod")
    assert auth.ok(reply := auth.exchange(wire)), reply
    read_line = partial(rapid_read_line, wire)

    def clip(s: str, n: int) -> str:
        return s if len(s) <= n else s[:n]

    def command(c: str) -> tuple[bool, str]:
        wire.send(rapid_string(c + line_end.decode("ascii")).encode("ascii"))  # SocketSend \Str
        reply = read_line()
        return clip(reply, 2) == "OK", reply

    def parse_xyz(reply: str) -> list[float] | None:
        if clip(reply, 3) != "OK ":
            return None
        vals = [rapid_strtoval(f) for f in reply[3:].split(",")]
        return vals if len(vals) == 3 and None not in vals else None  # type: ignore[return-value]

    ok, reply = command(begin)
    assert ok, reply
    while True:
        ok, reply = command("CAL NEXT")
        assert ok, reply
        if reply == "OK DONE":
            break
        vals = parse_xyz(reply)
        assert vals is not None, rapid_string("CAL NEXT: no x,y,z in " + clip(reply, 52))
        c = rapid_string("CAL POINT " + ",".join(rapid_numtostr(v, dec) for v in vals))
        ok, reply = command(c)
        if not ok:
            if clip(reply, 10) == "ERR moving":
                ok, reply = command(c)
            if not ok:
                messages.append(rapid_string("eyetohand: point skipped: " + clip(reply, 54)))
    ok, end = command("CAL END")
    messages.append(
        rapid_string(("eyetohand: calibrated: " if ok else "eyetohand: stopped: ") + clip(end, 57))
    )
    return {"ok": ok, "end": end, "messages": messages}


def test_abb_rapid(tmp_path, cell_file):
    """ABB: commands sent with CR LF by SocketSend; replies read byte by byte; END's reply, with the
    model's name first, is not put through StrToVal (it stopped the program after the calibration
    was saved); every message quoting a real server ERR stays within RAPID's 80 characters."""
    text = program("abb/EyetohandCollect.mod")
    begin = short_plan(one(r'CONST string BEGIN_CMD := "([^"]+)";', text).group(1))
    assert int(one(r"CONST num PORT := (\d+);", text).group(1)) == 5000
    escapes = one(r'SocketSend sock \\Str:=cmd \+ "((?:\\[0-9A-F]{2})+)";', text).group(1)
    line_end = bytes(int(h, 16) for h in re.findall(r"\\([0-9A-F]{2})", escapes))
    assert line_end == b"\r\n"
    dec = {int(d) for d in re.findall(r"NumToStr\(vals\{\d\}, (\d+)\)", text)}
    assert len(dec) == 1
    # the END reply as RAPID would have parsed it before: the model's name is not a num
    assert rapid_strtoval("homography-radial") is None
    srv = serve(tmp_path, cell_file, "--token", program_auth("abb/EyetohandCollect.mod").token)
    wire = Wire(srv.tcp_port)
    try:
        out = abb_run(wire, begin, line_end, dec.pop())
        assert out["ok"], out
        assert re.fullmatch(rf"OK [a-z-]+,{N_RECORDED},\d+\.\d{{4}},\d+\.\d{{4}}", out["end"]), out
        assert out["messages"][:-1] == [], out["messages"]
        assert out["messages"][-1] == f"eyetohand: calibrated: {out['end']}"
        assert wire.sent[1] == begin.encode() + b"\r\n" and all(s.endswith(b"\r\n") for s in wire.sent)
    finally:
        wire.close()
        srv.stop()


def test_abb_rapid_skips_a_pose_outside_the_view(tmp_path, cell_file):
    """A rectangle with a corner outside the view: RAPID's skip message quoting the server's real ERR
    is cut to 80 characters, the other poses are recorded and END calibrates."""
    text = program("abb/EyetohandCollect.mod")
    begin = short_plan(one(r'CONST string BEGIN_CMD := "([^"]+)";', text).group(1))
    begin = re.sub(r",grid:3x3,[-0-9.,]+,([0-9.]+)$", f",grid:3x3,{OUTSIDE_RECT},\\1", begin)
    assert OUTSIDE_RECT in begin, begin
    srv = serve(tmp_path, cell_file, "--token", program_auth("abb/EyetohandCollect.mod").token)
    wire = Wire(srv.tcp_port)
    try:
        out = abb_run(wire, begin, b"\r\n", 4)
        assert out["ok"], out
        assert re.fullmatch(r"OK [a-z-]+,8,\d+\.\d{4},\d+\.\d{4}", out["end"]), out
        skipped = out["messages"][:-1]
        assert len(skipped) == 1 and len(skipped[0]) == 80, skipped
        assert skipped[0].startswith("eyetohand: point skipped: ERR outside the image")
    finally:
        wire.close()
        srv.stop()


@pytest.mark.parametrize("cr_item", [b"\r\n", b"\r", b"\n"], ids=["crlf", "cr", "lf"])
def test_fanuc_karel(tmp_path, cell_file, cr_item):
    """FANUC: WRITE (line, CR) sends the line ended by the CR item — a CR, LF or CR LF (the manual's
    text we have does not say which bytes; the exchange works with each); replies are read byte by
    byte to LF into STRING[128]; CNV_STR_REAL reads NEXT's numbers; END's reply is only shown."""
    text = program("fanuc/eth_cal.kl")
    begin = short_plan(one(r"BEGIN_CMD = '([^']+)'", text).group(1))
    assert int(one(r"SERVER_PORT = (\d+)", text).group(1)) == 5000
    one(r"OPEN FILE sock \('RW', HOST_TAG\)", text)
    assert one(r"HOST_TAG = '(C\d):'", text).group(1) == "C3"
    assert "$HOSTC_CFG[3].$SERVER_PORT" in text
    one(r"WRITE sock \(line, CR\)", text)  # the CR item ends the line and sends the buffer
    assert not re.search(r"ROUTINE command\b", text, re.I)  # COMMAND is a reserved word
    assert "$GROUP[1].$UTOOL = " in text and "$GROUP[1].$UFRAME = " in text
    length, digits = (int(v) for v in one(r"CNV_REAL_STR\(v, (\d+), (\d+), s\)", text).groups())
    reply_len = int(one(r"reply : STRING\[(\d+)\]", text).group(1))
    auth = program_auth("fanuc/eth_cal.kl", cr_item)
    srv = serve(tmp_path, cell_file, "--token", auth.token)
    wire = Wire(srv.tcp_port)
    try:

        def send_cmd(line: str) -> tuple[bool, str]:
            wire.send(line.encode("ascii") + cr_item)
            reply = karel_read_line(wire, reply_len)
            return reply[:2] == "OK", reply

        assert auth.ok(r := auth.exchange(wire)), r
        assert send_cmd(begin)[0]
        n, skipped = 0, []
        while True:
            ok, reply = send_cmd("CAL NEXT")
            assert ok, reply
            if reply == "OK DONE":
                break
            vals = [karel_cnv_str_real(f) for f in reply[3:].split(",")]
            assert len(vals) == 3 and None not in vals, reply
            cmd = "CAL POINT " + ",".join(karel_cnv_real_str(v, length, digits) for v in vals)
            assert len(cmd) <= 128
            ok, reply = send_cmd(cmd)
            if not ok and reply[:10] == "ERR moving":
                ok, reply = send_cmd(cmd)
            if ok:
                n += 1
            else:
                skipped.append(reply[:40])
        ok, end = send_cmd("CAL END")
        assert ok and n == N_RECORDED and end.startswith("OK ") and len(end) <= reply_len, end
        assert skipped == []
        assert karel_cnv_str_real(end[3:].split(",")[0]) is None  # why END's reply is not parsed
    finally:
        wire.close()
        srv.stop()


def test_kuka_eki(tmp_path, cell_file):
    """KUKA: one EKI_Send per command, to which EthernetKRL appends the EOS (LF) itself; replies cut
    at the EOS. The old program's extra send of a bare LF became an empty line, which the server
    answers with an ERR: the FIFO would have handed that ERR to the next command."""
    src = program("kuka/eyetohand_collect.src")
    xml = program("kuka/EyetohandCal.xml")
    assert int(one(r"<PORT>(\d+)</PORT>", xml).group(1)) == 5000
    elem = one(r'<RECEIVE>.*<ELEMENT Tag="Reply" Type="STREAM" EOS="([\d,]+)" Size="(\d+)"', xml, re.S)
    eos = bytes(int(b) for b in elem.group(1).split(","))
    size = int(elem.group(2))
    assert eos == b"\n"
    command_fn = one(r"DEFFCT BOOL Command(.*?)ENDFCT", src, re.S).group(1)
    assert len(re.findall(r"EKI_Send\(", command_fn)) == 1, "one EKI_Send per command"
    assert len(re.findall(r"EKI_Send\(", code(src, ";"))) == 1
    begin = short_plan(one(r'StrCopy\(cmd\[\], "(CAL BEGIN [^"]+)"\)', src).group(1))
    point_fmt = one(r'SWRITE\(cmd\[\], st, offset, "([^"]+)"', src).group(1)
    sread = one(r'offset = (\d+)\s*;[^\n]*\n\s*SREAD\(reply\[\], st, offset, "([^"]+)"', src)
    auth = program_auth("kuka/eyetohand_collect.src")
    srv = serve(tmp_path, cell_file, "--token", auth.token)
    wire = Wire(srv.tcp_port)
    try:
        assert auth.ok(r := auth.exchange(wire)), r

        def command(line: str) -> tuple[bool, str]:
            wire.send(eki_send(line.encode("ascii").ljust(128, b"\0"), eos))  # cmd[128] after StrClear
            answer = eki_receive(wire, eos, size).rstrip("\r\n")
            return answer.startswith("OK"), answer

        assert command(begin)[0]
        n, skipped = 0, []
        while True:
            ok, reply = command("CAL NEXT")
            assert ok, reply
            if reply.upper() == "OK DONE":
                break
            xyz = krl_sread_reals(reply, int(sread.group(1)), sread.group(2))
            assert len(xyz) == 3, reply  # st.HITS = 3
            ok, reply = command(point_fmt % tuple(xyz))
            if not ok and reply.upper().startswith("ERR MOVING"):
                ok, reply = command(point_fmt % tuple(xyz))
            n += ok
            skipped += [] if ok else [reply]
        ok, end = command("CAL END")
        assert ok and n == N_RECORDED and len(skipped) == N_SKIPPED, (end, skipped)
        assert all(s.endswith(b"\n") and s.count(b"\n") == 1 and len(s) > 1 for s in wire.sent)
        # the trap: what a second, bare-LF send (an empty line) would have got from the server
        wire.send(eki_send(b"\0", eos))
        assert eki_receive(wire, eos, size).startswith("ERR")
    finally:
        wire.close()
        srv.stop()


def test_epson_spel(tmp_path, cell_file):
    """Epson: Print # ends each line with the port's terminator (SetNet: LF); Line Input # reads to
    it; FmtStr$ formats the POINT numbers; Move keeps U, V, W (no XY(), CP only as a bare option)."""
    text = program("epson/EyetohandCollect.prg")
    net = one(r'SetNet #201, "[\d.]+", (\d+), (CRLF|CR|LF), NONE, 0', text)
    assert int(net.group(1)) == 5000
    terminator = {"CR": b"\r", "LF": b"\n", "CRLF": b"\r\n"}[net.group(2)]
    assert terminator == b"\n"
    begin = short_plan(one(r'Cmd\("(CAL BEGIN [^"]+)"\)', text).group(1))
    fmt = one(r'FmtStr\$\(v, "([^"]+)"\)', text).group(1)
    assert not re.search(r"CP (On|Off)\s*(?:'.*)?$", text.split("CP Off\n", 1)[1], re.M)
    assert not re.search(r"\bXY\(", code(text, "'")) and "Move Here :X(x) :Y(y) :Z(z)" in text
    auth = program_auth("epson/EyetohandCollect.prg")
    srv = serve(tmp_path, cell_file, "--token", auth.token)
    wire = Wire(srv.tcp_port)
    try:
        assert auth.ok(r := auth.exchange(wire)), r

        def cmd(line: str) -> tuple[bool, str, list[float]]:
            wire.send(line.encode("ascii") + terminator)  # Print #201, line$
            reply = spel_line_input(wire, terminator)
            if reply.endswith("\r"):
                reply = reply[:-1]
            vals = (
                [spel_val(t) for t in reply[3:].split(",")]
                if reply[:2] == "OK" and len(reply) > 3 and reply != "OK DONE"
                else []
            )
            return reply[:2] == "OK", reply, vals

        assert cmd(begin)[0]
        n, skipped = 0, []
        while True:
            ok, reply, vals = cmd("CAL NEXT")
            assert ok, reply
            if reply == "OK DONE":
                break
            assert len(vals) == 3, reply
            point = "CAL POINT " + ",".join(spel_fmtstr(v, fmt) for v in vals)
            ok, reply, _ = cmd(point)
            if not ok and reply.find("ERR moving") == 0:  # InStr(...) = 1
                ok, reply, _ = cmd(point)
            n += ok
            skipped += [] if ok else [reply]
        ok, end, _ = cmd("CAL END")
        assert ok and n == N_RECORDED and len(skipped) == N_SKIPPED, (end, skipped)
        assert all(s.endswith(b"\n") and not s.endswith(b"\r\n") for s in wire.sent)
    finally:
        wire.close()
        srv.stop()


# ---- robot_client.py ---------------------------------------------------------------------------------


@pytest.mark.long
def test_robot_client_documented_negative_rect(tmp_path, cell_file):
    """The form ``--rect -40,570,60,650`` (a value that starts with '-'; README's rectangle no longer
    does) is accepted; its corner (-40,650) is outside this cell's view, so 8 of 9 are recorded. The
    token from ``--token-file``: AUTH is the first line."""
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-robot-token\n")
    srv = serve(tmp_path, cell_file, "--token-file", str(token_file))
    try:
        client = subprocess.run(
            [
                sys.executable,
                str(ROBOTS / "robot_client.py"),
                "--token-file",
                str(token_file),
                "--tcp",
                f"127.0.0.1:{srv.tcp_port}",
                "--name",
                "cell1",
                "--plan",
                PLAN,
                "--rect",
                "-40,570,60,650",
                "--z",
                "150",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            env=src_env(),
        )
        assert client.returncode == 0, client.stdout + client.stderr
        replies = [ln[2:] for ln in client.stdout.splitlines() if ln.startswith("< ")]
        assert replies[-1].startswith("OK ") and ",8," in replies[-1], replies
        sent = [ln[2:] for ln in client.stdout.splitlines() if ln.startswith("> ")]
        assert sent[0] == f"CAL BEGIN cell1,{PLAN},-40.0000,570.0000,60.0000,650.0000,150.0000"
    finally:
        srv.stop()


@pytest.mark.parametrize("script", ["robot_client.py", "pick_client.py"])
@pytest.mark.parametrize("reply_format", ["plain", "ur"])
def test_python_clients_stop_on_a_wrong_token(script, reply_format, servers):
    """EYETOHAND_TOKEN wrong: one line on stderr that names the refused token and where to set it,
    exit status 2, no traceback (plain "ERR send 'AUTH..." and ur "(-14,...)" alike)."""
    srv = servers[reply_format == "ur", "wrong"]
    client = subprocess.run(
        [sys.executable, str(ROBOTS / script), "--tcp", f"127.0.0.1:{srv.tcp_port}"]
        + (
            ["--name", "cell1", "--rect", "0,570,70,650", "--z", "150"] if script == "robot_client.py" else []
        ),
        capture_output=True,
        text=True,
        timeout=60,
        env={**src_env(), "EYETOHAND_TOKEN": "a-wrong-token-here"},
    )
    assert client.returncode == 2, client.stdout + client.stderr
    assert "Traceback" not in client.stderr and client.stderr.strip().count("\n") == 0, client.stderr
    assert "refused the token (AUTH, code -14)" in client.stderr and "EYETOHAND_TOKEN" in client.stderr


def test_robot_client_ctrl_c_is_one_line_and_130():
    """SIGINT while the robot waits for a reply: one line on stderr, exit status 130, no traceback."""
    listener = socket.create_server(("127.0.0.1", 0))
    accepted = threading.Event()
    conns: list[socket.socket] = []

    def accept():
        conns.append(listener.accept()[0])  # never answers
        accepted.set()

    threading.Thread(target=accept, daemon=True).start()
    proc = subprocess.Popen(
        [
            sys.executable,
            str(ROBOTS / "robot_client.py"),
            "--tcp",
            f"127.0.0.1:{listener.getsockname()[1]}",
            "--name",
            "cell1",
            "--rect",
            "-40,570,60,650",
            "--z",
            "150",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=src_env(),
        # a shell without job control starts background children with SIGINT ignored (CI run with
        # `&`): restore it, as a terminal's Ctrl-C finds it
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        assert accepted.wait(20), "robot_client did not connect"
        time.sleep(0.3)  # in recv, waiting for BEGIN's reply
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        for c in conns:
            c.close()
        listener.close()
    assert proc.returncode == 130, (proc.returncode, err)
    assert "Traceback" not in err
    assert err.strip().count("\n") == 0 and "interrupted" in err, err
