"""Geometric calibration from steel-ball phantom scans: per-view projection matrices and the
vibration correction later scans of the same protocol reconstruct with."""
