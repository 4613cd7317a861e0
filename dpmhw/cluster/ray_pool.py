"""Blocks of passes (and any other independent work) as Ray tasks, and `render_passes`, which
sends a render's blocks here or renders them in this process (`passes.render_local`).

`RayPool()` starts a local Ray instance on this machine (2 CPUs); `RayPool("ray://head:10001")`
or `RayPool("head:6379")` joins an existing cluster. Tasks are plain Ray tasks with
`max_retries`: when a worker process or a whole machine is lost, Ray runs its tasks again
elsewhere, and since a block is a pure function of (scene, time, seed, passes) the image is
unchanged. The scene travels inside the task as data (meshes as arrays, put once in Ray's object
store per render): workers never open a scene or mesh file, so no shared disk is needed.
"""

from __future__ import annotations

import uuid
from typing import Any, Callable, Iterable, Iterator

from dpmhw.cluster import INSTALL_HINT, ClusterError
from dpmhw.cluster.passes import Block, BlockResult, PassSum, plan, render_block, render_local
from dpmhw.render.digest import renderer_digest

LOCAL_CPUS = 2
MAX_RETRIES = 3  # re-runs of a task whose worker died (not of tasks that raised)


def import_ray():
    try:
        import ray
    except ModuleNotFoundError:
        raise ClusterError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def _call(fn: Callable, shared: Any, item: Any) -> Any:
    return fn(shared, item)


class RayPool:
    """A connection to Ray; `map` runs fn(shared, item) per item as tasks and yields results as
    they finish. Shuts down only a Ray instance it started itself."""

    def __init__(self, address: str | None = None, local_cpus: int = LOCAL_CPUS):
        ray = import_ray()
        self.address = address or None
        self._owned = False
        if not ray.is_initialized():
            try:
                if self.address is None:
                    # "local": a new instance, even on a machine that has joined a cluster with `ray start`
                    ray.init(address="local", num_cpus=local_cpus, include_dashboard=False, log_to_driver=False)
                else:
                    ray.init(address=self.address, log_to_driver=False)
            except ConnectionError as exc:
                raise ClusterError(f"cannot reach the Ray cluster at {self.address}: {exc} (a cluster with token "
                                   "authentication, Ray's default since 2.59, also needs RAY_AUTH_MODE=token here and its "
                                   "~/.ray/auth_token: docs/cluster.md)") from None
            self._owned = True
        self._ray = ray
        self._remote = ray.remote(_call)
        self._largest_node = 0.0  # CPUs of the largest node, looked up when a task needs more

    @property
    def cpus(self) -> int:
        return int(self._ray.cluster_resources().get("CPU", 0))

    def submit(self, fn: Callable, item: Any, shared: Any = None, num_cpus: float = 1, max_retries: int = MAX_RETRIES):
        """One task fn(shared, item); `shared` may be an ObjectRef from `put` (resolved on the worker)."""
        if num_cpus > self._largest_node:  # look again (nodes may have joined); Ray would queue it forever
            self._largest_node = max((n["Resources"].get("CPU", 0) for n in self._ray.nodes() if n["Alive"]), default=0)
            if num_cpus > self._largest_node:
                raise ClusterError(f"--threads {num_cpus:g}: a task needs that many CPUs on one node, and the largest "
                                   f"node of this cluster has {self._largest_node:g}")
        return self._remote.options(num_cpus=num_cpus, max_retries=max_retries, retry_exceptions=False).remote(fn, shared, item)

    def put(self, obj: Any):
        return self._ray.put(obj)

    def wait_one(self, pending: list) -> tuple[Any, Any, list]:
        """(finished task, its result, the tasks still pending)."""
        done, pending = self._ray.wait(pending, num_returns=1)
        return done[0], self._ray.get(done[0]), pending

    def cancel(self, pending: list) -> None:
        for ref in pending:
            self._ray.cancel(ref, force=False)

    def map(self, fn: Callable, items: Iterable, shared: Any = None, num_cpus: float = 1,
            max_retries: int = MAX_RETRIES) -> Iterator[tuple[int, Any]]:
        """(index of the item, fn(shared, item)) in order of completion. `shared` goes into the
        object store once for all tasks. Closing the iterator early cancels what is left."""
        shared_ref = self.put(shared)
        index = {self.submit(fn, item, shared_ref, num_cpus, max_retries): i for i, item in enumerate(items)}
        pending = list(index)
        try:
            while pending:
                ref, result, pending = self.wait_one(pending)
                yield index[ref], result
        finally:
            self.cancel(pending)

    def close(self) -> None:
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()
        self._owned = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def connect(address: str | None) -> RayPool | None:
    """The CLI's --ray ADDRESS: None (no --ray) → None; 'local' → a Ray instance on this
    machine; anything else (ray://HOST:10001, HOST:6379, auto) → that cluster."""
    if address is None:
        return None
    return RayPool(None if address == "local" else address)


# ----------------------------------------------------------------------------------------------
# rendering blocks on workers

_integrators: dict = {}  # per worker process: the integrator of the render it last worked on


def _worker_integrator(token: str, scene, threads: int, options: dict, renderer: str):
    """Reuse the BVHs, caches and compiled kernels across the blocks of one render; a worker
    keeps one integrator at a time, so memory stays bounded however many renders it serves.
    A worker whose renderer source differs from the driver's would give another image: refused."""
    from dpmhw.render.integrator import PathIntegrator

    key = (token, threads, tuple(sorted(options.items())))
    if key not in _integrators:
        mine = renderer_digest()
        if mine != renderer:
            raise ClusterError(f"a worker's renderer ({mine}) differs from the driver's ({renderer}): "
                               "install the same dpmhw on every node")
        for old in _integrators.values():
            old.close()
        _integrators.clear()
        _integrators[key] = PathIntegrator(scene, threads=threads, **options)
    return _integrators[key]


def render_block_task(shared: tuple, item: tuple) -> BlockResult:
    """Ray task body: one block of one render. `shared` = (token, scene, renderer digest),
    `item` = (time, block, threads, integrator options)."""
    token, scene, renderer = shared
    time, block, threads, options = item
    return render_block(_worker_integrator(token, scene, threads, options, renderer), time, block)


def render_on_ray(pool: RayPool, scene, time: float, seed: int, spp: int, threads: int = 1,
                  progress: Callable[[int, int], None] | None = None, should_stop: Callable[[], bool] | None = None,
                  task: Callable = render_block_task, integrator_options: dict | None = None) -> PassSum:
    """The blocks of a render as tasks of `threads` CPUs each, folded in block order as they come
    back (`progress(passes done, spp)` after each). On `should_stop` the rest is cancelled and the
    sum holds the blocks folded so far. `task` is the task body (tests wrap it);
    `integrator_options` go to every worker's PathIntegrator, as they must to the local one's."""
    blocks: list[Block] = plan(seed, spp)
    total = PassSum(blocks)
    done = 0
    items = [(float(time), b, int(threads), dict(integrator_options or {})) for b in blocks]
    results = pool.map(task, items, shared=(uuid.uuid4().hex, scene, renderer_digest()), num_cpus=threads)
    try:
        for _, result in results:
            total.add(result)
            done += result.spp
            if progress is not None:
                progress(done, spp)
            if should_stop is not None and not total.complete and should_stop():
                break
    finally:
        results.close()
    return total


def render_passes(scene, time: float, seed: int, spp: int, integrator=None, pool=None, threads: int = 2,
                  progress: Callable[[int, int], None] | None = None, integrator_options: dict | None = None) -> PassSum:
    """The summed render wherever it runs: as Ray tasks of `threads` CPUs on `pool` (a RayPool),
    else on `integrator`, else on an integrator of its own; `integrator_options` (keyword
    arguments of PathIntegrator) apply to the last two. The same image in every case."""
    if pool is not None:
        return render_on_ray(pool, scene, time, seed, spp, threads=threads, progress=progress,
                             integrator_options=integrator_options)
    if integrator is not None:
        return render_local(integrator, time, seed, spp, progress=progress)
    from dpmhw.render.integrator import PathIntegrator

    with PathIntegrator(scene, threads=threads, **(integrator_options or {})) as own:
        return render_local(own, time, seed, spp, progress=progress)
