"""WAV → features: chirp detection, association with the robot's events, GCC-PHAT TDOA-M/TDOA-S, SRP-PHAT DOA."""
from .extract import extract_features

__all__ = ["extract_features"]
