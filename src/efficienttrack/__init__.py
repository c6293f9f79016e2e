"""EfficientTrack: high-precision excavator trajectory tracking from learned closed-loop dynamics.

Importing the package registers the Gymnasium environments ``EfficientTrack/ClosedLoop-v0`` and
``EfficientTrack/OpenLoop-v0`` (:mod:`efficienttrack.envs`) when gymnasium is installed; without it (a torch- and
gymnasium-free runtime install) the package imports all the same.
"""

__version__ = "0.1.0"

try:
    import gymnasium  # noqa: F401  (only to learn whether it is installed)
except ImportError:
    pass
else:
    from efficienttrack.envs import register_envs

    register_envs()
