"""SuperTrack (Fussell et al. 2021): a world model learnt online and a policy trained through it (:mod:`.train`)."""

from efficienttrack.baselines.supertrack.settings import SUPERTRACK_PRESETS, SuperTrackSettings, supertrack_settings
from efficienttrack.baselines.supertrack.train import train_supertrack

__all__ = ["SUPERTRACK_PRESETS", "SuperTrackSettings", "supertrack_settings", "train_supertrack"]
