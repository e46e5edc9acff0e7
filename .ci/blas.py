"""Which BLAS kernel NumPy's OpenBLAS runs, and another this CPU can run, for .ci/run.

OpenBLAS picks a kernel per CPU (or takes OPENBLAS_CORETYPE); each sums in its own order, so a test whose
tolerance is one kernel's last bits passes on one machine and fails on another. .ci/run runs the
numerical tests (pytest -m numeric) a second time under a different kernel to catch such a test here.

    python .ci/blas.py info    one line: each BLAS library, its version, kernel and threads
    python .ci/blas.py other   an OPENBLAS_CORETYPE this CPU supports whose kernel differs from the
                               current one (nothing, when there is none)
"""

from __future__ import annotations

import os
import subprocess
import sys

# OPENBLAS_CORETYPE names, newest first, with the CPU flag each needs (x86-64 only; elsewhere: none)
CANDIDATES = (("SkylakeX", "avx512f"), ("Haswell", "avx2"), ("Sandybridge", "avx"), ("Nehalem", "sse4_2"))


def kernels() -> list[str]:
    import numpy  # noqa: F401  (loads NumPy's OpenBLAS)
    import scipy.linalg  # noqa: F401  (and SciPy's, a library of its own)
    import threadpoolctl

    return [
        f"{i['internal_api']} {i.get('version')} {i.get('architecture')} ({i['num_threads']} threads)"
        for i in threadpoolctl.threadpool_info()
        if i.get("user_api") == "blas"
    ]


def architecture(env: dict[str, str]) -> str:
    """The kernels NumPy's BLAS runs in a fresh interpreter with ``env`` ("" where it fails)."""
    code = "import numpy, threadpoolctl as t; print([i.get('architecture') for i in t.threadpool_info()])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else ""


def other() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((line.split(":", 1)[1].split() for line in fh if line.startswith("flags")), [])
    except OSError:
        return ""
    now = architecture(dict(os.environ))
    for name, flag in CANDIDATES:
        if flag in flags:
            arch = architecture({**os.environ, "OPENBLAS_CORETYPE": name})
            if arch and arch != now and "None" not in arch:
                return name
    return ""


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "info"
    print("; ".join(kernels()) if what == "info" else other())
