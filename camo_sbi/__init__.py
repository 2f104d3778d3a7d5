"""camo_sbi: infer joint limits from observed reaching trajectories (CAMO, ABC-SMC, NPE)."""

__version__ = "0.1.0"
