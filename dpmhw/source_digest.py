"""A digest of a tree of Python sources: what keys a cache of things those sources produce (the
renderer's references, numba's kernels)."""

from __future__ import annotations

import hashlib
from collections.abc import Collection
from pathlib import Path

__all__ = ["source_digest"]


def source_digest(root: Path, seed: bytes = b"", skip_top: Collection[str] = ()) -> str:
    """sha256 (hex) of `seed` and, for every .py file under `root` in path order, its path
    relative to `root` and its bytes; files named in `skip_top` directly in `root` are left out."""
    h = hashlib.sha256(seed)
    for path in sorted(root.rglob("*.py")):
        if path.parent == root and path.name in skip_top:
            continue
        h.update(path.relative_to(root).as_posix().encode() + path.read_bytes())
    return h.hexdigest()
