"""examples/robots/ur/eyetohand_plate.script against the real server process, byte for byte.

No UR controller runs here, so the program's exchange is replayed (as tests/test_robot_programs.py does
for the collection programs): what it sends — the AUTH line, its commands in order, the PLATE line, the
TOUCH lines with the pose read in metres and sent in millimetres, the CR LF line end — is read out of the
program's own text; the replies are read with URScript's socket_read_ascii_float rule. The server is
``eyetohand serve --camera sim:… --reply-format ur --token …``; the virtual cell's camera shows a rendered
chessboard (``SIM PLATE``, sent by the test as a person lays the plate down), and the robot's readings of
the pointer are the simulation's corners in the robot frame with 0.05 mm noise per axis. The stored
calibration must map the simulation's check points within their sigma."""

from __future__ import annotations

import re

import numpy as np
from helpers import ROBOTS, ServeProcess
from test_robot_programs import Wire, one, ur_socket_read_ascii_float, ur_str_of_float

from eyetohand.calibration import Calibration
from eyetohand.sim.cell import load_cell
from eyetohand.sim.plate import simulate_plate
from eyetohand.vision import PlateSpec

REL = "ur/eyetohand_plate.script"
PLATE_SEED = 1
NOISE_MM = 0.05


class Program:
    """What the program sends, read out of its text."""

    def __init__(self):
        text = (ROBOTS / REL).read_text()
        code = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
        self.token = one(r'^\s*TOKEN = "([^"]+)"', text, re.M).group(1)
        self.port = int(one(r"^\s*PORT = (\d+)", text, re.M).group(1))
        self.plate = one(r'^\s*PLATE = "(CAL PLATE [^"]+)"', text, re.M).group(1)
        cmd_def = one(r"def cmd\(line\):(.*?)\n  end", code, re.S).group(1)
        self.line_end = bytes(int(b) for b in re.findall(r'socket_send_byte\((\d+), "cam"\)', cmd_def))
        self.n_read = int(one(r'socket_read_ascii_float\((\d+), "cam"', cmd_def).group(1))
        auth = one(r"def auth\(\):(.*?)\n  end\n", code, re.S).group(1)
        one(r'socket_send_string\(str_cat\("AUTH ", TOKEN\), "cam"\)', auth)
        assert re.findall(r'socket_send_byte\((\d+), "cam"\)', auth) == ["13", "10"]
        self.auth_read = int(one(r'socket_read_ascii_float\((\d+), "cam"', auth).group(1))
        self.code_14 = int(one(r"r\[1\] == (-\d+):", auth).group(1))
        touch = one(r"def touch\(label\):(.*?)\n  end\n", code, re.S).group(1)
        # the TOUCH line: "CAL TOUCH " + label + "," + x,y,z of the TCP pose in metres x 1000
        one(
            r'str_cat\(str_cat\(str_cat\("CAL TOUCH ", label\), ","\),\s*xyz_text\(tcp\[0\] \* 1000, '
            r"tcp\[1\] \* 1000, tcp\[2\] \* 1000\)\)",
            touch,
        )
        one(r"tcp = get_actual_tcp_pose\(\)", touch)
        assert touch.index("end_freedrive_mode()") < touch.index("get_actual_tcp_pose()")
        one(r'return str_cat\(str_cat\(str_cat\(str_cat\(x, ","\), y\), ","\), z\)', code)
        # the main program's steps, in order: ("cmd", line) or ("touch", label)
        main = code[code.index("\n  auth()") :]
        self.steps = [
            ("touch", m.group(3)) if m.group(3) else ("cmd", m.group(1) or self.plate)
            for m in re.finditer(r'cmd\("([^"]+)"\)|cmd\((PLATE)\)|touch\("([A-Z0-9a-z]+)"\)', main)
        ]


def test_the_plate_program_commissions_the_cell(tmp_path, cell_file):
    prog = Program()
    assert prog.port == 5000 and prog.line_end == b"\r\n" and prog.n_read == 4
    assert prog.steps == [
        ("cmd", "CAL ABORT"),
        ("cmd", prog.plate),
        ("touch", "A"),
        ("touch", "B"),
        ("touch", "C"),
        ("touch", "D"),
        ("cmd", "CAL END"),
        ("cmd", "CAL ABORT"),  # only after a refused END
    ]
    spec = PlateSpec.parse(prog.plate.split()[2].split(",")[0])
    sim = simulate_plate(load_cell(cell_file), spec, seed=PLATE_SEED, render=False, n_check=40)
    world_mm = sim.placement.to_robot(spec.points_mm())
    labels = spec.corner_labels()
    rng = np.random.default_rng(7)
    srv = ServeProcess(
        tmp_path / "data",
        "--camera",
        f"sim:{cell_file}?seed=5",
        "--reply-format",
        "ur",
        "--token",
        prog.token,
    )
    try:
        lay = Wire(srv.tcp_port)  # a person lays the plate under the camera (the simulator's command)
        lay.send(f"AUTH {prog.token}\r\n".encode())
        assert lay.read_until(b"\n").startswith(b"(1,")
        lay.send(f"SIM PLATE {spec.text},{PLATE_SEED}\r\n".encode())
        assert lay.read_until(b"\n").startswith(b"(1,54,")  # OK 54 (points), in the ur format
        lay.close()

        wire = Wire(srv.tcp_port)

        def send_line(line: str) -> None:
            wire.send(line.encode("ascii"))  # socket_send_string: no line end
            for b in prog.line_end:
                wire.send(bytes([b]))  # socket_send_byte

        def cmd(line: str) -> list[float]:
            send_line(line)
            r = ur_socket_read_ascii_float(wire, prog.n_read)
            assert r[0] == prog.n_read, f"{line!r}: socket_read_ascii_float gave {r}"
            return r

        send_line(f"AUTH {prog.token}")
        r = ur_socket_read_ascii_float(wire, prog.auth_read)
        assert r[0] == prog.auth_read and r[1] == 1 and r[1] != prog.code_14, r
        replies = []
        for kind, arg in prog.steps[:-1]:  # the last ABORT runs only after a refused END
            if kind == "cmd":
                replies.append(cmd(arg))
                continue
            tcp_m = (world_mm[labels[arg]] + rng.normal(0, NOISE_MM, 3)) / 1000  # get_actual_tcp_pose
            xyz = ",".join(ur_str_of_float(v * 1000) for v in tcp_m)  # str_cat of tcp[i] * 1000
            replies.append(cmd(f"CAL TOUCH {arg},{xyz}"))
        abort, plate, *touched, end = replies
        assert abort[1] == -7  # no session was open: the program goes on
        assert plate[1:] == [1, 54, 4, 0], plate
        for k, (r, label) in enumerate(zip(touched, "ABCD", strict=True), start=1):
            assert r[1] == 1 and r[2] == k, r
            assert (
                np.hypot(r[3] - sim.true_uv_px[labels[label], 0], r[4] - sim.true_uv_px[labels[label], 1])
                < 0.2
            )
        assert end[1] == 1 and end[2] == 4 and 0 < end[3] <= end[4] < 4 * NOISE_MM, end
        wire.close()
    finally:
        srv.stop()
    from eyetohand.server.storage import Store

    st = Store(tmp_path / "data")
    try:
        vers = st.versions(st.find("cell1").id)
        cal = Calibration.from_dict(vers[-1].calibration, "stored")
    finally:
        st.close()
    assert len(vers) == 1 and cal.plate is not None and cal.plate.spec == spec
    assert [t.id for t in cal.plate.touches] == list("ABCD")
    check = np.loadtxt(sim.check_csv.splitlines()[1:], delimiter=",", usecols=range(5))
    m = cal.map(check[:, :2])
    err = np.linalg.norm(m.xyz_mm[:, :2] - check[:, 2:4], axis=1)
    assert m.sigma_mm is not None and np.all(err < 4 * m.sigma_mm), (err.max(), m.sigma_mm.min())


def test_the_plate_program_stops_on_a_wrong_token(tmp_path, cell_file):
    prog = Program()
    srv = ServeProcess(
        tmp_path / "data",
        "--camera",
        f"sim:{cell_file}?seed=5",
        "--reply-format",
        "ur",
        "--token",
        "another-token-1",
    )
    try:
        wire = Wire(srv.tcp_port, timeout_s=20)
        wire.send(f"AUTH {prog.token}".encode())
        for b in prog.line_end:
            wire.send(bytes([b]))
        r = ur_socket_read_ascii_float(wire, prog.auth_read)
        assert r[0] == prog.auth_read and r[1] == prog.code_14, r  # the program's own test: "refused"
        wire.close()
    finally:
        srv.stop()
