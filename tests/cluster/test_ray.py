"""Renders split over a local Ray instance (2 CPUs): exact, robust to lost workers, no shared disk.

Skipped when Ray is not installed (`pip install 'dpmhw[cluster]'`; CI installs it)."""

import json
import os
import shutil

import numpy as np
import pytest

pytest.importorskip("ray", reason="Ray is not installed: the cluster extra, pip install 'dpmhw[cluster]'")

from typer.testing import CliRunner  # noqa: E402

from dpmhw.cli import _register, app  # noqa: E402
from dpmhw.cluster.passes import PASSES_PER_BLOCK, render_local  # noqa: E402
from dpmhw.cluster.ray_pool import RayPool, render_block_task, render_on_ray  # noqa: E402
from dpmhw.render.integrator import PathIntegrator  # noqa: E402
from dpmhw.scene_file import load_scene  # noqa: E402

SPP = 3 * PASSES_PER_BLOCK - 3  # three blocks, the last one short
TIME = 0.1  # the wedge is turning


@pytest.fixture(scope="module")
def pool():
    """One local Ray instance for the module (its start-up costs seconds)."""
    with RayPool(local_cpus=2) as p:
        yield p


def _local(scene, seed=11, spp=SPP):
    with PathIntegrator(scene, threads=2) as integ:
        return render_local(integ, TIME, seed, spp)


def test_render_split_over_ray_is_the_local_render_bit_for_bit(pool, scene):
    local = _local(scene)
    seen = []
    remote = render_on_ray(pool, scene, TIME, 11, SPP, threads=1, progress=lambda done, total: seen.append((done, total)))
    assert remote.spp == local.spp == SPP and remote.complete
    assert np.array_equal(remote.radiance, local.radiance)
    assert np.array_equal(remote.object_id, local.object_id)
    assert remote.nonfinite_samples == local.nonfinite_samples == 0
    assert len(seen) == 3 and seen[-1] == (SPP, SPP)  # one report per block, as it came back
    assert all(a[0] < b[0] for a, b in zip(seen, seen[1:]))
    assert not np.array_equal(remote.radiance, _local(scene, seed=12).radiance)


def test_cli_with_ray_writes_the_same_image_as_without(pool, scene_file, tmp_path):
    _register()
    runner = CliRunner()
    outs = {}
    for name, extra in (("local", []), ("ray", ["--ray", "--threads", "1"])):  # a bare --ray: a local Ray instance
        outs[name] = tmp_path / f"{name}.npy"
        result = runner.invoke(app, ["render", str(scene_file), "--spp", str(SPP), "--seed", "4", "--time", str(TIME),
                                     "--out", str(outs[name]), *extra])
        assert result.exit_code == 0, result.output
    assert np.array_equal(np.load(outs["local"]), np.load(outs["ray"]))
    meta = json.loads((tmp_path / "ray.npy.json").read_text())
    assert meta["spp"] == SPP and meta["ray"] == "local"


def test_a_killed_worker_is_replaced_and_the_image_is_still_exact(pool, scene, tmp_path):
    marker = str(tmp_path / "killed-once")

    def dies_on_first_attempt(shared, item):
        block = item[1]
        if block.index == 1 and not os.path.exists(marker):
            with open(marker, "w") as f:
                f.write(str(os.getpid()))
            os._exit(1)  # the worker process dies mid-task, as when a machine drops out
        return render_block_task(shared, item)

    remote = render_on_ray(pool, scene, TIME, 11, SPP, threads=1, task=dies_on_first_attempt)
    assert os.path.exists(marker), "the first attempt of block 1 should have killed its worker"
    assert remote.spp == SPP
    assert np.array_equal(remote.radiance, _local(scene).radiance)


def test_relative_mesh_path_renders_on_a_worker_elsewhere_without_the_file(pool, scene_file, tmp_path):
    scene = load_scene(scene_file)  # meshes/wedge.obj, relative to the scene's folder
    local = _local(scene)
    shutil.move(scene_file.parent, tmp_path / "moved-away")  # no copy of the mesh where the scene said
    assert not scene_file.exists()

    def where(shared, item):
        return os.getcwd(), os.path.exists(os.path.join(os.getcwd(), "meshes", "wedge.obj"))

    (_, (cwd, mesh_there)), = pool.map(where, [None])
    assert os.path.realpath(cwd) != os.path.realpath(scene_file.parent) and not mesh_there
    remote = render_on_ray(pool, scene, TIME, 11, SPP, threads=1)
    assert np.array_equal(remote.radiance, local.radiance)


def test_bench_quality_on_ray_matches_local_and_its_references_are_reused_locally(pool, tmp_path):
    import dataclasses

    from dpmhw.benchmarks.quality import QualityConfig, format_table, run_quality
    from dpmhw.benchmarks.references import ReferenceCache
    from dpmhw.benchmarks.quality_ray import run_units_on_ray
    from dpmhw.sequence import scaled_scene

    cfg = dataclasses.replace(
        QualityConfig.quick(), parts=("static", "dynamic"), scale=1 / 32, ref_spp=PASSES_PER_BLOCK + 4, dynamic_ref_spp=4, static_spp=(1, 2), spp_repeats=1,
        alphas=(0.5,), eval_frames=1, modes=("same-pixel",), dynamic_fps=(947.0, 60.0), dynamic_eval_times=(0.02, 0.04), threads=1)
    on_ray = run_quality(cfg, cache_dir=tmp_path / "cluster-cache", pool=pool,
                         run_units=lambda units, cache, progress: run_units_on_ray(pool, units, cache, progress))
    assert on_ray["references"]["rendered"] == 1 + 2 + 2 and on_ray["ray"]["address"] == "local"
    assert [t["fps"] for t in on_ray["dynamic"]["timelines"]] == [947.0, 60.0]
    cpu = on_ray["cpu_seconds"]  # the workers' CPU, which no process here accounts for
    assert cpu["ray_references"] > 0 and cpu["ray_units"] > 0 and "ray units" in format_table(on_ray)
    # the same cache keys: a local run finds every reference the cluster rendered
    local = run_quality(cfg, cache_dir=tmp_path / "cluster-cache")
    assert local["references"]["rendered"] == 0 and local["references"]["cache_hits"] == 5
    assert list(local["cpu_seconds"]) == ["this_process"]

    def psnrs(result):
        return [r["psnr_samples"] for r in result["static"]["rows"]] + \
               [r["psnr_samples"] for t in result["dynamic"]["timelines"] for r in t["rows"]]

    assert psnrs(on_ray) == psnrs(local)
    # and what the cluster rendered is what this machine renders for that key
    scene = scaled_scene(load_scene(cfg.static_scene), cfg.scale)
    here = ReferenceCache(tmp_path / "local-cache", threads=2).get(scene, cfg.static_scene, 0.0, cfg.ref_spp)
    there = ReferenceCache(tmp_path / "cluster-cache").get(scene, cfg.static_scene, 0.0, cfg.ref_spp)
    assert np.array_equal(here["radiance"], there["radiance"]) and np.array_equal(here["object_id"], there["object_id"])


def test_a_worker_with_another_renderer_is_refused(pool, scene):
    from dpmhw.cluster import ClusterError

    def as_if_another_version(shared, item):
        token, scene, _ = shared
        return render_block_task((token, scene, "0123456789abcdef"), item)

    with pytest.raises(ClusterError, match="differs from the driver's"):
        render_on_ray(pool, scene, TIME, 11, SPP, threads=1, task=as_if_another_version)


def test_more_threads_than_any_node_has_is_an_error_not_a_hang(pool, scene):
    from dpmhw.cluster import ClusterError

    with pytest.raises(ClusterError, match="--threads 3"):
        render_on_ray(pool, scene, TIME, 11, SPP, threads=3)


def test_integrator_options_reach_every_worker(pool, scene):
    options = {"mis_last": False}  # a PathIntegrator keyword that changes the image of this glossy scene
    with PathIntegrator(scene, threads=2, **options) as integ:
        local = render_local(integ, TIME, 11, SPP)
    remote = render_on_ray(pool, scene, TIME, 11, SPP, threads=1, integrator_options=options)
    assert np.array_equal(remote.radiance, local.radiance)
    assert not np.array_equal(remote.radiance, _local(scene).radiance)
