"""One :class:`eyetohand.positioning.Served` protocol for what every positioning transport serves: a
served calibration written here, knowing nothing of the server's kinds (file, stored, none yet), is
driven through the TCP line service, the Modbus register map, OPC UA's state and LOCATE's refusal —
and the transports ask it only through the protocol (no ``isinstance`` of a kind, no ``getattr``)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from helpers import PAPER, records

from eyetohand import calibrate
from eyetohand.cell import ErrorCode, Refusal
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import (
    FixedCalibration,
    Identity,
    LineServer,
    ModbusService,
    PendingCalibration,
    Served,
    Status,
    locate_parts,
    state_of,
)
from eyetohand.positioning import registers as R
from eyetohand.server.stored import StoredCalibration

SRC = Path(__file__).resolve().parents[1] / "src" / "eyetohand"


class Switchable:
    """A served calibration of this test's own: its name and version, and a problem it is told."""

    def __init__(self, cal, name: str = "fake cell", version: int = 7):
        self.cal = cal
        self.name, self.version = name, version
        self.refusal: Refusal | None = None
        self.polls = 0

    def problem(self) -> Refusal | None:
        return self.refusal

    def identity(self) -> Identity:
        return Identity(self.name, self.version)

    def version_line(self) -> str:
        return f"OK {self.name},{self.version},fake"

    def describe(self) -> str:
        return "a fake"

    def poll(self) -> None:
        self.polls += 1


@pytest.fixture(scope="module")
def cal():
    pairs = pairs_from_records(records(PAPER / "calibration_points.csv"))
    return calibrate(pairs, "homography", "lm", loo=False)


@pytest.fixture
def served(cal):
    return Switchable(cal)


def _centre(cal) -> tuple[float, float]:
    c = cal.region.hull_px.mean(axis=0)
    return round(float(c[0]), 3), round(float(c[1]), 3)


def test_every_kind_is_a_served(cal, tmp_path):
    assert isinstance(FixedCalibration(cal, "cell.json"), Served)
    assert isinstance(PendingCalibration("cell"), Served)
    assert isinstance(Switchable(cal), Served)
    assert FixedCalibration(cal, "/x/cell.json").identity() == Identity("cell", 0, "/x/cell.json")
    assert PendingCalibration("cell").identity() == Identity("cell")
    assert PendingCalibration(None).problem().code is ErrorCode.NO_CALIBRATION  # type: ignore[union-attr]
    assert {"problem", "identity", "version_line", "describe", "poll"} <= set(dir(StoredCalibration))


def test_the_line_service_asks_only_the_protocol(served, cal):
    server = LineServer(served, "127.0.0.1", 0)
    u, v = _centre(cal)
    assert server.reply(b"VERSION") == b"OK fake cell,7,fake\n"
    got = [float(x) for x in server.reply(f"{u},{v}".encode()).decode().split(",")]
    want = cal.image_to_robot(np.array([[u, v]]))[0]
    np.testing.assert_array_equal(got, want)  # the mapping line's numbers: the library's, unchanged
    served.refusal = Refusal(ErrorCode.DATABASE, "database replaced or missing: the fake's words")
    assert server.reply(f"{u},{v}".encode()) == b"ERR database replaced or missing: the fake's words\n"
    assert server.reply(b"VERSION") == b"ERR database replaced or missing: the fake's words\n"
    served.refusal = None
    served.cal = None  # says nothing is wrong but has nothing: refused, never a crash
    assert server.reply(f"{u},{v}".encode()).startswith(b"ERR no calibration")


def test_modbus_names_and_refuses_through_the_protocol(served, cal):
    svc = ModbusService(lambda: served, "127.0.0.1", 0)
    u, v = _centre(cal)
    regs = [0] * R.LOCATE_END
    block = R.encode_request(R.Request(1, u, v, None, None, False))
    assert svc.respond(block, regs)
    got = R.decode_result(regs[R.RESULT_ID : R.RESULT_END])
    assert (got["status"], got["name"], got["version"]) == (0, "fake cell", 7)
    want = cal.image_to_robot(np.array([[u, v]]))[0]
    assert abs(got["x"] - want[0]) <= 1e-3 and abs(got["y"] - want[1]) <= 1e-3  # µm registers
    served.refusal = Refusal(ErrorCode.NO_CALIBRATION, "calibration 'fake cell' was deleted")
    served.version = 8
    assert svc.respond(R.encode_request(R.Request(2, u, v, None, None, False)), regs)
    got = R.decode_result(regs[R.RESULT_ID : R.RESULT_END])
    assert (got["status"], got["version"]) == (int(Status.NO_CALIBRATION), 8)


def test_opcua_state_and_locate_follow_the_problem(served):
    assert state_of(served) == "Ready"
    served.refusal = Refusal(ErrorCode.NO_CALIBRATION, "calibration 'x' was deleted")
    assert state_of(served) == "NoCalibration"
    served.refusal = Refusal(ErrorCode.NO_CALIBRATION, "version 3 of 'x' cannot be read", broken=True)
    assert state_of(served) == "Error"  # from the refusal's kind, not from its words
    res = locate_parts(np.zeros((48, 64), np.uint8), served)
    assert res.status is Status.NO_CALIBRATION and res.reason == "version 3 of 'x' cannot be read"


def _kind_checks(tree: ast.AST) -> list[int]:
    kinds = {"FixedCalibration", "PendingCalibration", "StoredCalibration"}
    out = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "id", None) == "isinstance"
            and len(node.args) == 2
        ):
            names = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
            if names & kinds:
                out.append(node.lineno)
    return out


def test_no_transport_asks_which_kind_it_serves():
    bad = []
    for path in sorted([*(SRC / "positioning").glob("*.py"), *(SRC / "server").rglob("*.py")]):
        lines = _kind_checks(ast.parse(path.read_text(encoding="utf-8")))
        bad += [f"{path.relative_to(SRC)} line {n}" for n in lines]
    assert not bad, "isinstance of a served kind (use the Served protocol's methods): " + ", ".join(bad)


def test_the_kind_check_finds_one():
    assert _kind_checks(ast.parse("if isinstance(src, (int, StoredCalibration)):\n    pass\n")) == [1]


def _err_decoders(tree: ast.AST) -> list[int]:
    """Lines that read an ``ERR`` reply's text: ``x.startswith("ERR…")``, ``x[:3] == "ERR"`` and
    ``"ERR" in x`` style tests of a str or bytes constant starting with ERR."""

    def err(node) -> bool:
        return (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str | bytes)
            and node.value[:3] in ("ERR", b"ERR")
        )

    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr in ("startswith", "removeprefix") and node.args and err(node.args[0]):
                out.append(node.lineno)
        elif isinstance(node, ast.Compare) and (err(node.left) or any(err(c) for c in node.comparators)):
            out.append(node.lineno)
    return out


def test_no_module_reads_an_err_reply_for_its_meaning():
    """A refusal's kind travels as a code (Refusal, CommandError): no library module decodes ERR text."""
    bad = []
    for path in sorted(SRC.rglob("*.py")):
        bad += [
            f"{path.relative_to(SRC)} line {n}" for n in _err_decoders(ast.parse(path.read_text("utf-8")))
        ]
    assert not bad, "ERR text read back for a meaning: " + ", ".join(bad)


def test_the_err_check_finds_one():
    code = 'if text.startswith("ERR"):\n    pass\nok = data[:3] == b"ERR"\n'
    assert _err_decoders(ast.parse(code)) == [1, 3]


def test_serve_options_become_one_typed_config(cal, tmp_path):
    """check_options turns serve's parsed options into one frozen ServeConfig, addresses parsed, the
    calibration file proved and loaded once; the start-up wiring reads only it."""
    import dataclasses

    from eyetohand.cli import build_parser
    from eyetohand.core import output_units
    from eyetohand.server.config import ServeConfig
    from eyetohand.server.startup import check_options

    path = cal.save(tmp_path / "cell.json")
    argv = ["serve", "--tcp", "127.0.0.1:7001", "--calibration", str(path), "--units", "m"]
    argv += ["--modbus", "127.0.0.1:5020", "--robot-address", "10.0.0.9", "--reply-format", "ur"]
    cfg = check_options(build_parser().parse_args(argv))
    assert isinstance(cfg, ServeConfig)
    assert (cfg.tcp, cfg.modbus, cfg.opcua, cfg.plc_wanted) == (
        ("127.0.0.1", 7001),
        ("127.0.0.1", 5020),
        None,
        True,
    )
    assert (cfg.reply_format, cfg.units, cfg.robot_addresses) == (
        "ur",
        output_units("m", None),
        ("10.0.0.9",),
    )
    assert cfg.calibration_file is not None
    assert cfg.calibration_file.identity().file == str(path.resolve())
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.port = 1  # type: ignore[misc]


def test_the_start_up_wiring_reads_no_namespace():
    """After check_options, serve's wiring takes the ServeConfig: no ``args.`` nor ``getattr(args``
    past it in server/startup.py (the checks before it read the namespace they check)."""
    text = (SRC / "server" / "startup.py").read_text(encoding="utf-8")
    wiring = text[text.index("def allowed_hosts(") :]
    wiring = wiring.replace(
        wiring[wiring.index("def _plc_wanted(") : wiring.index("def _served_calibration(")], ""
    )
    assert "args." not in wiring and "getattr(args" not in wiring
