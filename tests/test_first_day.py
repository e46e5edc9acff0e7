"""docs/first-day.md, run: every fenced ``sh`` block of the guide, in order, in one shell, in the virtual
cell (the rules the guide states at its top: ``sh hardware`` blocks with the camera set to ``sim:``,
``# robot at X Y Z`` turned into ``--pose X Y Z`` and ``# sim: COMMAND`` lines run; the ``sh service``
block in the background; ``sh setup`` and ``sh root`` not run). The guide cannot rot: a command that
changed, an option that went, a file that moved fails here."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time

import pytest
from helpers import ROOT, free_port, src_env

GUIDE = ROOT / "docs" / "first-day.md"
BLOCK = re.compile(r"^```sh( [a-z]+)?\n(.*?)^```$", re.M | re.S)
KINDS = {"", "hardware", "service", "setup", "root"}


def blocks() -> list[tuple[str, str]]:
    found = [((m.group(1) or "").strip(), m.group(2)) for m in BLOCK.finditer(GUIDE.read_text())]
    assert found and {k for k, _ in found} <= KINDS, {k for k, _ in found}
    return found


def simulated(kind: str, text: str, port: int) -> str:
    """A block as the test runs it (the substitutions the guide documents)."""
    if kind == "hardware":
        text = re.sub(r"^CAMERA=\S+", "CAMERA=sim:", text, flags=re.M)
        at = r"\s*# robot at (-?[\d.]+) (-?[\d.]+) (-?[\d.]+)\s*$"
        text = re.sub(at, r" --pose \1 \2 \3", text, flags=re.M)
        text = re.sub(r"^# sim: ", "", text, flags=re.M)
    text = text.replace("--port 8765", "--port 0").replace("127.0.0.1:5000", f"127.0.0.1:{port}")
    text = text.replace("127.0.0.1:8765", "127.0.0.1:$HTTP")  # the workbench's port, read from serve.log
    return text


def script(port: int) -> str:
    lines = ["set -euo pipefail", 'mark() { echo "@@ $1 $(date +%s.%N)"; }']
    for i, (kind, text) in enumerate(blocks()):
        if kind in ("setup", "root"):
            continue
        body = simulated(kind, text, port)
        lines.append(f"mark block{i}")
        if kind == "service":
            lines.append(f"( {body.strip()} ) > serve.log 2>&1 &")
            lines.append("SERVE=$!; trap 'kill -INT $SERVE 2>/dev/null; wait $SERVE || true' EXIT")
            lines.append("for _ in $(seq 600); do grep -q '^workbench:' serve.log && break; sleep 0.1; done")
            lines.append("grep '^TCP:' serve.log")
            lines.append("HTTP=$(sed -n 's|^workbench: http://[^:]*:\\([0-9]*\\)/.*|\\1|p' serve.log)")
            health = 'curl -sf "http://127.0.0.1:$HTTP/api/health" && echo && break'
            lines.append(f"for _ in $(seq 600); do {health}; sleep 0.1; done")
        else:
            lines.append(body)
    lines.append("mark end")
    return "\n".join(lines) + "\n"


def test_guide_blocks_follow_the_rules():
    kinds = [k for k, _ in blocks()]
    assert kinds.count("service") == 1 and "setup" in kinds and "root" in kinds
    for kind, text in blocks():
        if kind != "hardware":
            assert "# robot at" not in text and "# sim:" not in text, text
    readme = (ROOT / "README.md").read_text()
    first_link = re.search(r"\]\((docs/[^)]+)\)", readme)
    assert first_link and first_link.group(1) == "docs/first-day.md"
    quick = readme.split("## Quick start", 1)[1].split("```", 2)[1]
    assert quick.strip() == "make demo\nmake test"


@pytest.mark.slow
@pytest.mark.long
def test_the_first_day_guide_runs_in_the_virtual_cell(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "eyetohand"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m eyetohand.cli "$@"\n')
    shim.chmod(0o755)
    py = bin_dir / "python3"  # a venv's python found through a symlink would not know its venv
    py.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    py.chmod(0o755)
    env = {**src_env(), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    env["EXAMPLES"] = str(ROOT / "examples")
    t0 = time.monotonic()
    run = ["bash", "-c", script(free_port())]
    r = subprocess.run(run, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    elapsed = time.monotonic() - t0
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    out = r.stdout
    assert "right-handed, z up" in out
    assert re.search(r"^--rect -?\d+,\d+,-?\d+,\d+ --z 150$", out, re.M), out
    assert re.search(r"^< OK [a-z-]+,25,", out, re.M), out  # CAL END: 25 of 25 poses recorded
    assert re.search(r"^PASS \(", out, re.M), out  # the touch test
    marks = {m.group(1): float(m.group(2)) for m in re.finditer(r"^@@ (\S+) ([\d.]+)$", out, re.M)}
    service = next(i for i, (k, _) in enumerate(blocks()) if k == "service")
    collect = f"block{service + 1}"  # the robot's collection follows the service's start
    names = list(marks)
    after = names[names.index(collect) + 1]
    verified = next(i for i, (_, text) in enumerate(blocks()) if "eyetohand verify" in text)
    done = names[names.index(f"block{verified}") + 1]  # the guide goes on after the touch test (a plate)
    print(
        f"\nfirst-day guide in the virtual cell: {elapsed:.1f} s in all, first grab to verify "
        f"{marks[done] - marks[names[0]]:.1f} s, the collection {marks[after] - marks[collect]:.1f} s"
    )
