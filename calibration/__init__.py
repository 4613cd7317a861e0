"""Projector-camera calibration and the projector's pose in the tracker frame."""
