"""numba's cache is one directory per version of the package's sources: a kernel cached with
helpers from other modules inlined is never loaded after one of those helpers changed."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from dpmhw.kernel_cache import KEEP, configure
from dpmhw.source_digest import source_digest


def _package(root: Path) -> Path:
    pkg = root / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "kernels.py").write_text("def caller():\n    return helper()\n")
    (pkg / "sub" / "helpers.py").write_text("def helper():\n    return 1\n")
    (pkg / "notes.txt").write_text("not a source")
    return pkg


def test_the_digest_follows_every_source_file_and_nothing_else(tmp_path):
    pkg = _package(tmp_path)
    first = source_digest(pkg)
    assert source_digest(pkg) == first
    (pkg / "notes.txt").write_text("changed, but not a source")
    assert source_digest(pkg) == first
    (pkg / "sub" / "helpers.py").write_text("def helper():\n    return 2\n")  # a helper, not its caller
    changed = source_digest(pkg)
    assert changed != first
    (pkg / "sub" / "helpers.py").rename(pkg / "sub" / "other.py")  # same bytes in the same order, another module
    assert source_digest(pkg) not in (first, changed)


def test_a_changed_helper_gets_a_cache_of_its_own_and_old_versions_are_pruned(tmp_path):
    pkg = _package(tmp_path)
    env = {"DPMHW_CACHE": str(tmp_path / "cache")}
    dirs = []
    for version in range(KEEP + 2):
        (pkg / "sub" / "helpers.py").write_text(f"def helper():\n    return {version}\n")
        env.pop("NUMBA_CACHE_DIR", None)
        dirs.append(Path(configure(env, pkg)))
        assert env["NUMBA_CACHE_DIR"] == str(dirs[-1]) and dirs[-1].is_dir()
        assert dirs[-1].parent == tmp_path / "cache" / "kernels"
        os.utime(dirs[-1], (version, version))  # one a second apart, oldest first
    assert len(set(dirs)) == KEEP + 2
    env.pop("NUMBA_CACHE_DIR")
    assert Path(configure(env, pkg)) == dirs[-1]  # the same sources: the same cache, used last now
    assert sorted(p for p in dirs[-1].parent.iterdir()) == sorted(dirs[-KEEP:])


def test_a_cache_dir_set_by_the_user_is_left_alone(tmp_path):
    pkg = _package(tmp_path)
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "mine"), "DPMHW_CACHE": str(tmp_path / "cache")}
    assert configure(env, pkg) == str(tmp_path / "mine")
    assert env["NUMBA_CACHE_DIR"] == str(tmp_path / "mine") and not (tmp_path / "cache").exists()


def test_an_unwritable_cache_root_falls_back_to_this_versions_temporary_dir(tmp_path, monkeypatch):
    pkg = _package(tmp_path)
    (tmp_path / "a-file").write_text("")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    env = {"DPMHW_CACHE": str(tmp_path / "a-file")}  # a file: no directory can be made under it
    assert configure(env, pkg) == str(tmp_path / "tmp" / f"dpmhw-kernels-{source_digest(pkg)[:16]}")


def test_importing_dpmhw_points_numba_at_this_source_versions_cache(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["DPMHW_CACHE"] = str(tmp_path)
    code = ("import dpmhw, numba.core.config as c; from dpmhw.source_digest import source_digest; "
            "from dpmhw.kernel_cache import PACKAGE; print(c.CACHE_DIR); print(source_digest(PACKAGE)[:16])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == str(tmp_path / "kernels" / out[1])
