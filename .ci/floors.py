"""Print pip constraints that pin every ``>=`` floor of pyproject.toml to exactly that version.

``make floors`` installs the package with these constraints into a second venv and runs a quick
subset of the tests: a floor we state is a floor we have run. Extras named on the command line
(default: the ones a plain install and the quick tests use) add their floors too.
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

REQ = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[[^\]]*\])?\s*>=\s*([0-9][0-9A-Za-z.]*)")


def floors(pyproject: Path, extras: list[str]) -> dict[str, str]:
    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    reqs = list(project["dependencies"])
    for extra in extras:
        reqs += project["optional-dependencies"][extra]
    out: dict[str, str] = {}
    for req in reqs:
        m = REQ.match(req)
        if m is None:
            raise SystemExit(f"floors: {req!r} in pyproject.toml states no >= floor")
        out.setdefault(m.group(1).lower(), m.group(2))
    return out


if __name__ == "__main__":
    root = Path(__file__).resolve().parent.parent
    for name, version in floors(root / "pyproject.toml", sys.argv[1:]).items():
        print(f"{name}=={version}")
