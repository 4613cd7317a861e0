"""The renderer digest follows every source that shapes an image, in subpackages too, and no other."""

import shutil
from pathlib import Path

from dpmhw.render import digest


def test_the_digest_follows_the_ray_queries_and_ignores_the_gbuffer(tmp_path):
    tree = tmp_path / "render"
    shutil.copytree(Path(digest.__file__).parent, tree, ignore=shutil.ignore_patterns("__pycache__"))
    before = digest.renderer_digest(tree)
    assert digest.renderer_digest() == before  # the copy digests as the package does

    gbuffer = tree / "gbuffer.py"
    gbuffer.write_text(gbuffer.read_text() + "\n# not rendering\n")
    assert digest.renderer_digest(tree) == before

    capi = tree / "embree" / "capi.py"
    capi.write_text(capi.read_text() + "\n# a change in a subpackage\n")
    assert digest.renderer_digest(tree) != before
