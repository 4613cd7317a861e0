"""Errors the calibration pipeline raises; each names the input and says what to do."""

from __future__ import annotations

from dpmhw.errors import CalibrationError


class CaptureError(CalibrationError):
    """A capture folder is missing, incomplete, or holds unreadable/inconsistent images."""


class DegenerateViewsError(CalibrationError):
    """The board poses cannot constrain the model (too few, fronto-parallel, ...)."""
