"""The pick programs of examples/robots/ (``LOCATE``) against the real server process, byte for byte.

As tests/test_robot_programs.py does for the collection programs (its emulations of the controllers'
documented rules are imported from it): each program's LOCATE command, line end and number reading
are taken from its own text and replayed against ``eyetohand serve --camera sim:…`` calibrated by a
3x3 collection; the virtual table holds 12 parts, some outside the calibrated region. One cycle per
program: LOCATE, then LOCATE NEXT until DONE; each part the program accepts is "picked" on a side
connection (``SIM PICK``, standing in for the gripper) and must be there; the next LOCATE then finds
only the parts outside the region (count 0), which the program never gets. Each server runs with
``--token`` the program's own token, and each program's first line is its ``AUTH`` (read out of its
text by test_robot_programs.program_auth).
"""

from __future__ import annotations

import re
import sys

import pytest
from helpers import ROBOTS, SMALL_CELL_TOML, ServeProcess, view_square_mm
from test_robot_programs import (
    Wire,
    code,
    eki_receive,
    eki_send,
    karel_cnv_str_real,
    krl_sread_reals,
    one,
    program,
    program_auth,
    rapid_string,
    rapid_strtoval,
    spel_line_input,
    spel_val,
    ur_socket_read_ascii_float,
)

sys.path.insert(0, str(ROBOTS))
from robot_client import TcpLink, VirtualRobot  # noqa: E402

CELL = SMALL_CELL_TOML
SEED = 5
Z = 150.0


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A data folder whose calibration cell1 a 3x3 collection made (the server stopped again)."""
    import eyetohand.sim  # noqa: F401
    from eyetohand.vision import open_source

    root = tmp_path_factory.mktemp("pick")
    cell = root / "cell.toml"
    cell.write_text(CELL)
    srv = ServeProcess(root / "data", "--camera", f"sim:{cell}?seed={SEED}", "--calibration", "cell1")
    try:
        link = TcpLink("127.0.0.1", srv.tcp_port, timeout_s=60)
        cx, cy, h = view_square_mm(open_source(f"sim:{cell}").cell_camera.camera, Z, margin_px=40)
        out = VirtualRobot(link.send).run_plan("cell1", "grid:3x3", (cx - h, cy - h, cx + h, cy + h), Z)
        assert out["end"].startswith("OK ") and ",9," in out["end"], out
        link.close()
    finally:
        srv.stop()
    return root


class Cell:
    """The server on the calibrated data (``--token`` the program's), 12 parts on its table, a side
    connection (the gripper), and the program's connection after its AUTH."""

    def __init__(self, root, rel: str, *extra: str):
        auth = program_auth(rel)
        self.srv = ServeProcess(
            root / "data",
            "--camera",
            f"sim:{root / 'cell.toml'}?seed={SEED}",
            "--calibration",
            "cell1",
            "--token",
            auth.token,
            *extra,
        )
        self.side = TcpLink("127.0.0.1", self.srv.tcp_port, timeout_s=60, token=auth.token)
        # with --reply-format ur every reply on every connection is bracketed, the simulator's too
        self.ok = "(1," if "ur" in extra else "OK "
        placed = self.side.send(f"SIM PARTS 12,3,10,{Z}")
        assert placed == ("(1,12,0,0,0,0)" if "ur" in extra else "OK 12"), placed
        self.wire = Wire(self.srv.tcp_port)
        assert auth.ok(reply := auth.exchange(self.wire)), reply
        self.picked: list[str] = []

    def grip(self, x: float, y: float) -> None:
        reply = self.side.send(f"SIM PICK {x:.4f},{y:.4f}")
        assert reply.startswith(self.ok), reply
        self.picked.append(reply)

    def close(self) -> None:
        self.wire.close()
        self.side.close()
        self.srv.stop()


def run_cycle(cell: Cell, locate, next_part, max_sigma: float) -> tuple[int, int]:
    """LOCATE → count; NEXT until DONE, gripping each accepted part; LOCATE again → (count, its count)."""
    count = locate()
    assert count >= 1
    handed = 0
    while (part := next_part()) is not None:
        x, y, z, rz, sigma = part
        handed += 1
        assert z == Z and rz == 0
        if 0 <= sigma <= max_sigma:
            cell.grip(x, y)
    assert handed == count == len(cell.picked)
    return count, locate()


def test_ur_pick(calibrated):
    text = program("ur/eyetohand_pick.script")
    locate_cmd = one(r'LOCATE = "(LOCATE [^"]+)"', text).group(1)
    cmd_def = one(r"def cmd\(line\):(.*?)\n  end", text, re.S).group(1)
    line_end = bytes(int(b) for b in re.findall(r'socket_send_byte\((\d+), "cam"\)', cmd_def))
    n_read = int(one(r'socket_read_ascii_float\((\d+), "cam"', cmd_def).group(1))
    max_sigma_m = float(one(r"MAX_SIGMA = ([\d.]+)", text).group(1))
    vision = one(r"# Vision side: +eyetohand serve (.*)$", text, re.M).group(1).split()
    serve_opts = vision[vision.index("--reply-format") :]  # what the script says the server runs with
    assert serve_opts == ["--reply-format", "ur", "--units", "m", "--angle-units", "rad"]
    assert line_end == b"\r\n" and n_read == 6
    assert 'cmd("LOCATE NEXT")' in text and "r[6] < 0 or r[6] > MAX_SIGMA" in text
    assert "down = p[r[2], r[3], r[4] + TOOL_DZ," in text  # metres as answered: no conversion
    cell = Cell(calibrated, "ur/eyetohand_pick.script", *serve_opts)
    try:

        def cmd(line: str) -> list[float]:
            cell.wire.send(line.encode("ascii"))
            for b in line_end:
                cell.wire.send(bytes([b]))
            r = ur_socket_read_ascii_float(cell.wire, n_read)
            assert r[0] == n_read, f"{line!r}: socket_read_ascii_float gave {r}"
            return r

        def locate() -> int:
            r = cmd(locate_cmd)
            assert r[1] == 1, r
            return int(r[2])

        def next_part():  # metres and radians, back in mm and deg for run_cycle's checks
            r = cmd("LOCATE NEXT")
            assert r[1] in (0, 1), r
            if r[1] == 0:
                return None
            sigma = r[6] if r[6] < 0 else round(r[6] * 1000, 4)
            return [round(r[2] * 1000, 4), round(r[3] * 1000, 4), round(r[4] * 1000, 4), r[5], sigma]

        first, again = run_cycle(cell, locate, next_part, max_sigma_m * 1000)
        assert again == 0
        assert cmd("LOCATE 0.012,0.008")[1] == -1  # refused: a negative code, six numbers still
    finally:
        cell.close()


def test_abb_pick(calibrated):
    text = program("abb/EyetohandPick.mod")
    locate_cmd = one(r'CONST string LOCATE_CMD := "([^"]+)";', text).group(1)
    max_sigma = float(one(r"CONST num MAX_SIGMA := ([\d.]+);", text).group(1))
    escapes = one(r'SocketSend sock \\Str:=cmd \+ "((?:\\[0-9A-F]{2})+)";', text).group(1)
    line_end = bytes(int(h, 16) for h in re.findall(r"\\([0-9A-F]{2})", escapes))
    one(r"ParseNums\(reply, 2\)", text)
    one(r"ParseNums\(reply, 5\)", text)
    cell = Cell(calibrated, "abb/EyetohandPick.mod")
    try:

        def command(c: str) -> str:
            cell.wire.send(rapid_string(c + line_end.decode("ascii")).encode("ascii"))
            line = ""
            while (ch := cell.wire.read_byte()) != b"\n":
                if ch != b"\r" and len(line) < 80:
                    line = rapid_string(line + ch.decode("ascii"))
            assert line[:2] == "OK", line
            return line

        def parse(reply: str, want: int) -> list[float]:
            assert reply[:3] == "OK "
            vals = [rapid_strtoval(f) for f in reply[3:].split(",")]
            assert len(vals) == want and None not in vals, reply
            return vals  # type: ignore[return-value]

        def next_part():
            reply = command("LOCATE NEXT")
            return None if reply == "OK DONE" else parse(reply, 5)

        _, again = run_cycle(cell, lambda: int(parse(command(locate_cmd), 2)[0]), next_part, max_sigma)
        assert again == 0
    finally:
        cell.close()


def test_fanuc_pick(calibrated):
    text = program("fanuc/eth_pick.kl")
    locate_cmd = one(r"LOCATE_CMD = '([^']+)'", text).group(1)
    max_sigma = float(one(r"MAX_SIGMA = ([\d.]+)", text).group(1))
    one(r"WRITE sock \(line, CR\)", text)
    reply_len = int(one(r"reply : STRING\[(\d+)\]", text).group(1))
    cell = Cell(calibrated, "fanuc/eth_pick.kl")
    try:

        def send_cmd(line: str) -> str:
            cell.wire.send(line.encode("ascii") + b"\r\n")
            reply = cell.wire.read_until(b"\n")[:-1].replace(b"\r", b"").decode("ascii")[:reply_len]
            assert reply[:2] == "OK", reply
            return reply

        def parse(reply: str, want: int) -> list[float]:
            vals = [karel_cnv_str_real(f) for f in reply[3:].split(",")]
            assert len(vals) == want and None not in vals, reply
            return vals  # type: ignore[return-value]

        def next_part():
            reply = send_cmd("LOCATE NEXT")
            return None if reply == "OK DONE" else parse(reply, 5)

        _, again = run_cycle(cell, lambda: int(parse(send_cmd(locate_cmd), 2)[0]), next_part, max_sigma)
        assert again == 0
    finally:
        cell.close()


def test_kuka_pick(calibrated):
    src = program("kuka/eyetohand_pick.src")
    xml = program("kuka/EyetohandCal.xml")
    elem = one(r'<RECEIVE>.*<ELEMENT Tag="Reply" Type="STREAM" EOS="([\d,]+)" Size="(\d+)"', xml, re.S)
    eos, size = bytes(int(b) for b in elem.group(1).split(",")), int(elem.group(2))
    assert len(re.findall(r"EKI_Send\(", code(src, ";"))) == 1
    locate_cmd = one(r'StrCopy\(cmd\[\], "(LOCATE \d[^"]*)"\)', src).group(1)
    fmts = re.findall(r'SREAD\(reply\[\], st, offset, "([^"]+)"', src)
    assert fmts == ["%f,%f", "%f,%f,%f,%f,%f"], fmts
    max_sigma = float(one(r"MAX_SIGMA = ([\d.]+)", src).group(1))
    cell = Cell(calibrated, "kuka/eyetohand_pick.src")
    try:

        def command(line: str) -> str:
            cell.wire.send(eki_send(line.encode("ascii").ljust(128, b"\0"), eos))
            answer = eki_receive(cell.wire, eos, size).rstrip("\r\n")
            assert answer.startswith("OK"), answer
            return answer

        def locate() -> int:
            vals = krl_sread_reals(command(locate_cmd), 3, fmts[0])
            assert len(vals) == 2  # st.HITS = 2
            return int(vals[0])

        def next_part():
            reply = command("LOCATE NEXT")
            if reply.upper() == "OK DONE":
                return None
            vals = krl_sread_reals(reply, 3, fmts[1])
            assert len(vals) == 5, reply  # st.HITS = 5
            return vals

        _, again = run_cycle(cell, locate, next_part, max_sigma)
        assert again == 0
    finally:
        cell.close()


def test_epson_pick(calibrated):
    text = program("epson/EyetohandPick.prg")
    net = one(r'SetNet #201, "[\d.]+", (\d+), (CRLF|CR|LF), NONE, 0', text)
    terminator = {"CR": b"\r", "LF": b"\n", "CRLF": b"\r\n"}[net.group(2)]
    locate_cmd = one(r'Cmd\("(LOCATE \d[^"]*)"\)', text).group(1)
    max_sigma = float(one(r"MAX_SIGMA = ([\d.]+)", text).group(1))
    one(r"If gCount <> 2 Then GoTo Fail", text)
    one(r"If gCount <> 5 Then GoTo Fail", text)
    cell = Cell(calibrated, "epson/EyetohandPick.prg")
    try:

        def cmd(line: str) -> tuple[str, list[float]]:
            cell.wire.send(line.encode("ascii") + terminator)
            reply = spel_line_input(cell.wire, terminator).rstrip("\r")
            assert reply[:2] == "OK", reply
            vals = (
                [spel_val(t) for t in reply[3:].split(",")] if len(reply) > 3 and reply != "OK DONE" else []
            )
            return reply, vals

        def locate() -> int:
            _, vals = cmd(locate_cmd)
            assert len(vals) == 2
            return int(vals[0])

        def next_part():
            reply, vals = cmd("LOCATE NEXT")
            if reply == "OK DONE":
                return None
            assert len(vals) == 5, reply
            return vals

        _, again = run_cycle(cell, locate, next_part, max_sigma)
        assert again == 0
    finally:
        cell.close()
