"""The one compiled part: a C loop for the lens-free planar maps of many pixels (src/eyetohand/_rows.c).

Optional — where it cannot be built (no C compiler) the package maps through NumPy and OpenCV: the
same numbers, slower (docs/performance.md). Everything else is in pyproject.toml.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "eyetohand._rows",
            sources=["src/eyetohand/_rows.c"],
            # -ffp-contract=off: no fused multiply-add, so the loop equals the NumPy paths bit for bit
            extra_compile_args=["-O3", "-ffp-contract=off"],
            optional=True,
        )
    ]
)
