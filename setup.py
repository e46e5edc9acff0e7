"""The compiled parts: three small C extensions (src/eyetohand/models/_rows.c, a loop for the lens-free planar
maps of many pixels; src/eyetohand/solve/_swarm.c, the hybrid PSO's swarm steps; src/eyetohand/geometry/_hull.c,
the calibrated region's test of many pixels).

Optional — where they cannot be built (no C compiler) the package runs the same steps in NumPy and
OpenCV: the same numbers, slower (docs/performance.md). Everything else is in pyproject.toml.
"""

from setuptools import Extension, setup


def _extension(package: str, name: str) -> Extension:
    return Extension(
        f"eyetohand.{package}.{name}",
        sources=[f"src/eyetohand/{package}/{name}.c"],
        include_dirs=["src/eyetohand"],  # _buffers.h, shared by all
        depends=["src/eyetohand/_buffers.h"],
        # -ffp-contract=off: no fused multiply-add, so the loops equal the NumPy paths bit for bit
        extra_compile_args=["-O3", "-ffp-contract=off"],
        optional=True,
    )


setup(ext_modules=[_extension("models", "_rows"), _extension("solve", "_swarm"), _extension("geometry", "_hull")])
