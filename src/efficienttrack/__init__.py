"""EfficientTrack: high-precision excavator trajectory tracking from learned closed-loop dynamics."""

__version__ = "0.1.0"
