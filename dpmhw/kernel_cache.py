"""Where numba keeps the compiled kernels: one directory per version of the package's sources.

numba checks a cached function against its own source file only, but a kernel carries the
machine code of the helpers it calls from other modules (inlined). After an upgrade that changed
a helper and not its caller, numba would load the caller with the old helper in it. So unless
`NUMBA_CACHE_DIR` is set (then whoever set it owns that cache), the cache is
`$DPMHW_CACHE/kernels/<digest of every .py file of the package>` (`$DPMHW_CACHE` defaults to
~/.cache/dpmhw; where that cannot be made, `dpmhw-kernels-<digest>` in the temporary directory):
any change to the sources compiles afresh, and reinstalling the same sources finds their
kernels again. The `KEEP` most recently used versions are kept.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import MutableMapping

from dpmhw.source_digest import source_digest

__all__ = ["KEEP", "cache_root", "configure"]

KEEP = 3  # source versions whose kernels stay on disk (a session's kernels take about 6 MB)
PACKAGE = Path(__file__).resolve().parent


def cache_root(environ: MutableMapping[str, str] = os.environ) -> Path:
    """dpmhw's own on-disk cache: `$DPMHW_CACHE`, else ~/.cache/dpmhw."""
    return Path(environ.get("DPMHW_CACHE") or Path.home() / ".cache" / "dpmhw")


def configure(environ: MutableMapping[str, str] = os.environ, package: Path = PACKAGE) -> str:
    """Point numba at this source version's cache unless `NUMBA_CACHE_DIR` is set; returns the
    directory. Called when dpmhw is imported, before any kernel is defined; child processes
    inherit the variable."""
    if environ.get("NUMBA_CACHE_DIR"):
        return environ["NUMBA_CACHE_DIR"]
    versions = cache_root(environ) / "kernels"
    digest = source_digest(package)[:16]
    here = versions / digest
    try:
        here.mkdir(parents=True, exist_ok=True)
        os.utime(here)  # most recently used
        for old in sorted((p for p in versions.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime)[:-KEEP]:
            shutil.rmtree(old, ignore_errors=True)
    except OSError:  # not writable: this version's place in the temporary directory (never numba's per-file one)
        here = Path(tempfile.gettempdir()) / f"dpmhw-kernels-{digest}"
    environ["NUMBA_CACHE_DIR"] = str(here)
    if environ is os.environ and "numba.core.config" in sys.modules:  # numba read its settings already
        sys.modules["numba.core.config"].reload_config()
    return str(here)
