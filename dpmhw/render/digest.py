"""A digest of the renderer's source: what keys cached references, and what a cluster's workers
must share with the driver to give the same image."""

from __future__ import annotations

from pathlib import Path

from dpmhw import __version__
from dpmhw.source_digest import source_digest

# neither changes a path-traced image: the native G-buffer, and this file
NOT_RENDERING = ("gbuffer.py", "digest.py")


def renderer_digest(root: Path | None = None) -> str:
    """The source digest of the version and `root`/**/*.py (default: dpmhw/render/) but
    NOT_RENDERING at its top, 16 hex digits."""
    root = Path(__file__).resolve().parent if root is None else root
    return source_digest(root, __version__.encode(), NOT_RENDERING)[:16]
