"""eyetohand: calibrate a fixed camera to an industrial robot."""

__version__ = "0.1.0"
