"""Reading and writing observed reaches (recordings) in the documented file format."""

from camo_sbi.io.recordings import Recording, load_goals, load_recording, load_recordings
from camo_sbi.io.resample import estimate_rate, resample_to_controller
from camo_sbi.io.schema import EE_COLUMNS, GOAL_COLUMNS, K_SIGMA, save_recordings

__all__ = ["EE_COLUMNS", "GOAL_COLUMNS", "K_SIGMA", "Recording", "estimate_rate", "load_goals", "load_recording",
           "load_recordings",
           "resample_to_controller", "save_recordings"]
