"""Exceptions a lab operator can act on: each names the file, the field and what was expected."""

from __future__ import annotations


class DpmhwError(Exception):
    """Base class of every error dpmhw raises on purpose."""


class SceneError(DpmhwError, ValueError):
    """A scene file (or a built-in scene) is invalid."""

    def __init__(self, source: str, field: str, message: str):
        self.source = source
        self.field = field
        super().__init__(f"{source}: {field}: {message}")


class RenderError(DpmhwError, RuntimeError):
    """The renderer met something it cannot handle (a bug or a broken scene)."""


class CalibrationError(DpmhwError, ValueError):
    """A calibration input (capture folder, calibration file) or view set cannot be used."""

    def __init__(self, source: str, field: str, message: str):
        self.source = source
        self.field = field
        super().__init__(f"{source}: {field}: {message}")
