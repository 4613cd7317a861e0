"""Which machine a figure was measured on: CPU model, cores, the vector ISA the CPU has, the one
numba generates code for (`NUMBA_CPU_NAME=znver2` builds AVX2 code on an AVX-512 machine) and
Embree's (`DPMHW_EMBREE_ISA=avx2` asks its device for AVX2). Figures from different machines
differ by 2-3x; a figure without these cannot be compared with another. On a virtual machine,
also how much CPU time the host gave to other guests while a figure was measured (`cpu_steal`):
a present path that holds on bare metal misses refreshes when its CPU is taken away."""

from __future__ import annotations

import functools
import os
import platform


def _cpuinfo() -> tuple[str, set[str]]:
    model, flags = "unknown CPU", set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name" and model == "unknown CPU":
                    model = value.strip()
                elif key == "flags" and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    return model, flags


def _isa(features) -> str:
    """The widest x86 vector ISA in a set of feature names (cpuinfo's `avx512f`, LLVM's `+avx512f`)."""
    names = {f.lstrip("+") for f in features if not f.startswith("-")}
    return "AVX-512" if "avx512f" in names else "AVX2" if "avx2" in names else "SSE" if "sse2" in names else "other"


@functools.cache
def machine_info() -> dict:
    """Flat keys: cpu_model, cores, cpu_isa, numba_cpu, numba_isa, embree_isa, python."""
    model, flags = _cpuinfo()
    info = {"cpu_model": model, "cores": os.cpu_count(), "cpu_isa": _isa(flags), "python": platform.python_version()}
    try:
        from numba.core.registry import cpu_target

        _, cpu, features = cpu_target.target_context.codegen().magic_tuple()
        info["numba_cpu"] = cpu
        info["numba_isa"] = _isa(features.split(",")) if features else f"{cpu}'s"
    except Exception as exc:  # numba missing or changed: say so rather than guess
        info["numba_cpu"] = info["numba_isa"] = f"unknown ({type(exc).__name__})"
    info["embree_isa"] = os.environ.get("DPMHW_EMBREE_ISA") or "native"
    return info


def cpu_ticks() -> tuple[int, ...] | None:
    """The machine's CPU time so far, in ticks per kind (/proc/stat's aggregate line: user, nice,
    system, idle, iowait, irq, softirq, steal, …), or None where there is no /proc/stat."""
    try:
        with open("/proc/stat") as f:
            head = f.readline().split()
    except OSError:
        return None
    if len(head) < 9 or head[0] != "cpu":
        return None
    return tuple(int(v) for v in head[1:9])


def cpu_steal(before: tuple[int, ...] | None, after: tuple[int, ...] | None) -> float | None:
    """The fraction (0-1) of all CPU time between two `cpu_ticks` readings that the hypervisor ran
    other guests on this VM's CPUs (steal); None without both readings or with no tick between."""
    if before is None or after is None:
        return None
    delta = [b - a for a, b in zip(before, after)]
    total = sum(delta)
    return round(delta[7] / total, 4) if total > 0 else None


def steal_percent(fraction: float | None) -> str:
    """A `cpu_steal` figure for a table: "2.5%", or "-" where there is none."""
    return "-" if fraction is None else f"{100 * fraction:.1f}%"


def machine_line() -> str:
    m = machine_info()
    return (f"machine: {m['cpu_model']}, {m['cores']} cores, {m['cpu_isa']}; numba code for {m['numba_cpu']} "
            f"({m['numba_isa']}), Embree ISA {m['embree_isa']}")


def avx2_features() -> str:
    """This host's LLVM feature string with AVX-512 (and AMX, AVX10) switched off: with
    `NUMBA_CPU_NAME=znver2 NUMBA_CPU_FEATURES=<this>` numba builds the AVX2 code an AVX2 lab PC
    runs. `NUMBA_CPU_NAME` alone is not enough: numba still passes the host's features, so LLVM
    keeps emitting AVX-512 instructions."""
    from llvmlite import binding

    off = ("avx512", "amx", "avx10")
    return ",".join(("-" if not on or name.startswith(off) else "+") + name
                    for name, on in binding.get_host_cpu_features().items())
