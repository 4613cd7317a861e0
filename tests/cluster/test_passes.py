"""The block decomposition of a render, without Ray: seeds, order-independent folding, stopping."""

import numpy as np
import pytest

from dpmhw.cluster.passes import PASSES_PER_BLOCK, BlockResult, PassSum, block_seed, plan, render_block, render_local
from dpmhw.render.integrator import PathIntegrator


def test_plan_covers_every_pass_once_with_distinct_seeds():
    blocks = plan(seed=7, spp=2 * PASSES_PER_BLOCK + 3)
    assert [b.passes for b in blocks] == [PASSES_PER_BLOCK, PASSES_PER_BLOCK, 3]
    assert [b.first_pass for b in blocks] == [0, PASSES_PER_BLOCK, 2 * PASSES_PER_BLOCK]
    assert blocks[0].seed == 7  # a render of ≤ 8 passes is the integrator's own render
    seeds = {b.seed for b in plan(7, 100 * PASSES_PER_BLOCK)} | {b.seed for b in plan(8, 100 * PASSES_PER_BLOCK)}
    assert len(seeds) == 200 and all(0 <= s < 2**63 for s in seeds)
    assert block_seed(7, 3) == block_seed(7, 3) != block_seed(8, 3)
    with pytest.raises(ValueError):
        plan(0, 0)


def test_small_render_is_the_integrators_render_and_order_of_arrival_does_not_matter(scene):
    with PathIntegrator(scene, threads=2) as integ:
        assert np.array_equal(render_local(integ, 0.0, 5, 6).radiance, integ.render(seed=5, spp=6).radiance)
        blocks = plan(5, 20)
        results = [render_block(integ, 0.0, b) for b in blocks]
        in_order = render_local(integ, 0.0, 5, 20)
    shuffled = PassSum(blocks)
    for r in (results[2], results[0], results[1]):
        shuffled.add(r)
    assert shuffled.complete and shuffled.spp == in_order.spp == 20
    assert np.array_equal(shuffled.radiance, in_order.radiance)
    assert np.array_equal(shuffled.object_id, in_order.object_id)
    # the mean of the blocks' means, weighted by their passes
    expected = sum(r.radiance.astype(np.float64) * r.spp for r in results) / 20
    assert np.array_equal(in_order.radiance, expected.astype(np.float32))
    with pytest.raises(ValueError):
        shuffled.add(results[1])


def test_stopping_keeps_the_finished_passes(scene):
    seen = []
    with PathIntegrator(scene) as integ:
        total = render_local(integ, 0.0, 3, 40, progress=lambda done, n: seen.append(done), should_stop=lambda: len(seen) >= 11)
        first = render_block(integ, 0.0, plan(3, 40)[0])
        partial = integ.render(seed=plan(3, 40)[1].seed, spp=3)
    assert total.spp == 11 and seen == list(range(1, 12))
    expected = (first.radiance.astype(np.float64) * 8 + partial.radiance.astype(np.float64) * 3) / 11
    assert np.array_equal(total.radiance, expected.astype(np.float32))


def test_a_gap_holds_later_blocks_back():
    blocks = plan(0, 24)
    total = PassSum(blocks)
    one = np.ones((2, 2, 3), np.float32)
    total.add(BlockResult(1, 8, one, 0, None, 0.0, 0.0))
    assert total.folded_blocks == 0 and total.spp == 0
    total.add(BlockResult(0, 8, 3 * one, 0, np.zeros((2, 2), np.int32), 0.0, 0.0))
    assert total.folded_blocks == 2 and total.spp == 16
    assert np.array_equal(total.radiance, 2 * one)


@pytest.mark.parametrize("command", [["render", "--spp", "2"], ["bench", "quality"]])
def test_ray_option_without_ray_says_how_to_install_it(command, scene_file, tmp_path, monkeypatch):
    import sys

    from typer.testing import CliRunner

    from dpmhw.cli import _register, app

    monkeypatch.setitem(sys.modules, "ray", None)  # as if the cluster extra were not installed
    _register()
    args = [command[0], str(scene_file), *command[1:]] if command[0] == "render" else command
    result = CliRunner().invoke(app, [*args, "--out" if command[0] == "render" else "--cache-dir", str(tmp_path / "x.npy"),
                                      "--ray", "local"])
    assert result.exit_code == 2, result.output
    assert "pip install 'dpmhw[cluster]'" in result.output
    assert not (tmp_path / "x.npy").exists()
