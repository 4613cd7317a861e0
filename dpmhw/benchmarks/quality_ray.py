"""`dpmhw bench quality --ray`: the bench's sweep units (static part, each dynamic timeline) as
Ray tasks (`run_units_on_ray`, the bench's UnitRunner), its references as blocks of passes on the
same cluster.

References stay where the reference cache is, on this machine: a unit task gets the references
it has asked for shipped in, and a unit that meets one it does not have returns the request
instead of a result; this machine then takes it from its cache or renders it over the cluster
(with the same key as a local render, so it is reused by local runs) and submits the unit again.
A unit asks for its references before its timeline, so a retry costs only its set-up.
"""

from __future__ import annotations

import time as _time
from typing import Callable

from dpmhw.benchmarks.quality import QualityConfig, run_unit
from dpmhw.benchmarks.references import REFERENCE_SEED, ReferenceCache
from dpmhw.cluster import ClusterError


class MissingReference(Exception):
    def __init__(self, request: tuple):
        super().__init__("reference not shipped")
        self.request = request  # (scene, scene_name, time, spp, seed, key options)


class ShippedReferences(ReferenceCache):
    """Worker side: only the references shipped with the task (key → arrays)."""

    def __init__(self, known: dict, threads: int):
        super().__init__(threads=threads)
        self.known = known

    def get(self, scene, scene_name: str, time: float, spp: int, seed: int = REFERENCE_SEED, integrator=None,
            **key_options) -> dict:
        """`key_options`: ReferenceCache's other keyed options (how the reference samples), passed on
        as they are, so a unit on Ray asks for the same reference as it would locally."""
        key, _ = self.key(scene, time, spp, seed, **key_options)
        if key not in self.known:
            raise MissingReference((scene, scene_name, time, spp, seed, key_options))
        self.hits += 1
        return self.known[key]


def run_unit_task(_shared, item: tuple) -> tuple[str, object, float]:
    """("done", (result parts, images), CPU s) or ("need", reference request, CPU s). The CPU
    time is the worker's: no process on the driver's machine accounts for it (Ray workers are not
    the driver's children, so not even `/usr/bin/time` of the command sees it)."""
    unit, known, renderer = item
    started = _time.process_time()
    cache = ShippedReferences(known, unit.threads)
    if cache.renderer != renderer:
        raise ClusterError(f"this worker's renderer ({cache.renderer}) differs from the driver's ({renderer}): "
                           "install the same dpmhw on every node")
    try:
        return "done", run_unit(unit, cache, lambda desc, done, total: None), _time.process_time() - started
    except MissingReference as missing:
        return "need", missing.request, _time.process_time() - started


def run_units_on_ray(pool, units: list[QualityConfig], cache: ReferenceCache,
                     progress: Callable) -> tuple[list[tuple[dict, dict]], float]:
    """Results of `units` in their order, and the CPU seconds their tasks took on the workers
    (every attempt). Each needed reference comes from `cache` (disk, or rendered over `pool` as
    blocks of passes while the other units keep running)."""
    known: list[dict] = [{} for _ in units]
    outcomes: list = [None] * len(units)
    cpu_seconds = 0.0

    def submit(i: int):
        return pool.submit(run_unit_task, (units[i], known[i], cache.renderer), num_cpus=units[i].threads)

    index = {submit(i): i for i in range(len(units))}
    pending = list(index)
    try:
        while pending:
            ref, (kind, value, cpu), pending = pool.wait_one(pending)
            i = index.pop(ref)
            cpu_seconds += cpu
            if kind == "done":
                outcomes[i] = value
                progress("bench units on Ray (static part, each dynamic timeline)", sum(o is not None for o in outcomes), len(units))
                continue
            scene, name, time, spp, seed, options = value
            key, _ = cache.key(scene, time, spp, seed, **options)
            if key in known[i]:
                raise ClusterError(f"unit {i} asked twice for reference {key}: keys differ between driver and worker")
            known[i][key] = cache.get(scene, name, time, spp, seed, **options)
            ref = submit(i)
            index[ref] = i
            pending.append(ref)
    finally:
        pool.cancel(pending)
    return outcomes, cpu_seconds
