"""The shipped systemd unit (examples/deploy/eyetohand.service, docs/deploy.md): systemd's own checker
accepts it, and its command line is one this eyetohand's ``serve`` accepts."""

from __future__ import annotations

import shlex
import shutil
import subprocess

import pytest
from helpers import ROOT

from eyetohand.cli import build_parser
from eyetohand.server.startup import check_options

UNIT = ROOT / "examples" / "deploy" / "eyetohand.service"
INSTALLED = "/opt/eyetohand/bin/eyetohand"  # where docs/deploy.md installs it


def exec_start(text: str) -> list[str]:
    """ExecStart's words, continuation lines joined, as systemd splits them (shell quoting rules)."""
    joined = text.replace("\\\n", " ")
    (line,) = [ln for ln in joined.splitlines() if ln.startswith("ExecStart=")]
    return shlex.split(line.removeprefix("ExecStart="))


def test_the_units_command_is_one_serve_accepts():
    argv = exec_start(UNIT.read_text())
    assert argv[0] == INSTALLED and argv[1] == "serve"
    args = build_parser().parse_args(argv[1:])
    args.token = "from-the-environment-file"  # EnvironmentFile=/etc/eyetohand.env: EYETOHAND_TOKEN
    check_options(args)  # the option checks serve runs before anything binds
    assert args.data == "/var/lib/eyetohand" and args.modbus and args.opcua and args.tcp
    assert [str(n) for n in args.modbus_allow] == ["10.0.0.20/32"]
    text = UNIT.read_text()
    for line in ("Restart=on-failure", "User=eyetohand", "StateDirectory=eyetohand"):
        assert f"\n{line}\n" in text, line


def test_the_unit_passes_systemd_analyze_verify(tmp_path):
    """``systemd-analyze verify`` on the unit as shipped, but for ExecStart's program, which it
    requires to exist: a stub stands at that place (the only line changed). It prints every problem
    (an unknown key, a bad value) and still exits 0 for most, so its output must be empty too."""
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip("systemd-analyze is not installed (make systemd-analyze: apt-get install systemd)")
    stub = tmp_path / "eyetohand"
    stub.write_text("#!/bin/sh\nexit 0\n")
    stub.chmod(0o755)
    unit = tmp_path / "eyetohand.service"
    unit.write_text(UNIT.read_text().replace(INSTALLED, str(stub)))
    r = subprocess.run([exe, "verify", str(unit)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and not r.stderr.strip() and not r.stdout.strip(), r.stderr + r.stdout
    bad = tmp_path / "bad.service"  # the checker is awake: a wrong value is reported
    bad.write_text(unit.read_text().replace("Restart=on-failure", "Restart=sometimes"))
    r = subprocess.run([exe, "verify", str(bad)], capture_output=True, text=True, timeout=120)
    assert "restart specifier" in r.stderr
