"""A digest of the renderer's source: what keys cached references, and what a cluster's workers
must share with the driver to give the same image."""

from __future__ import annotations

import hashlib
from pathlib import Path

from dpmhw import __version__

# neither changes a path-traced image: the native G-buffer, and this file
NOT_RENDERING = ("gbuffer.py", "digest.py")


def renderer_digest(root: Path | None = None) -> str:
    """sha256 of the version and `root`/**/*.py (default: dpmhw/render/) but NOT_RENDERING at
    its top, 16 hex digits."""
    h = hashlib.sha256(__version__.encode())
    root = Path(__file__).resolve().parent if root is None else root
    for p in sorted(root.rglob("*.py")):
        if p.name in NOT_RENDERING and p.parent == root:
            continue
        h.update(p.relative_to(root).as_posix().encode() + p.read_bytes())
    return h.hexdigest()[:16]
