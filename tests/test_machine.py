"""Every bench result names its machine; the ISA is read from feature names, not guessed."""

from __future__ import annotations

import json

from dpmhw.cli.apps import write_json
from dpmhw.machine import _isa, avx2_features, cpu_steal, cpu_ticks, machine_info


def test_isa_from_cpuinfo_flags_and_llvm_features():
    assert _isa({"sse2", "avx2", "avx512f"}) == "AVX-512"
    assert _isa(["+sse2", "+avx2", "-avx512f"]) == "AVX2"  # LLVM's string with AVX-512 switched off
    assert _isa({"sse2"}) == "SSE"


def test_avx2_features_switch_avx512_off_and_keep_the_rest():
    names = dict((f[1:], f[0]) for f in avx2_features().split(","))
    assert all(on == "-" for name, on in names.items() if name.startswith("avx512"))
    assert _isa(avx2_features().split(",")) in ("AVX2", "SSE", "other")


def test_bench_json_records_the_machine(tmp_path):
    m = machine_info()
    assert {"cpu_model", "cores", "cpu_isa", "numba_cpu", "numba_isa", "embree_isa"} <= set(m)
    data = json.loads(write_json({"fps": 60.0}, tmp_path / "a.json").read_text())
    assert data["machine"] == json.loads(json.dumps(m)) and data["fps"] == 60.0
    rows = json.loads(write_json([{"x": 1}, {"x": 2}], tmp_path / "b.json").read_text())
    assert [r["x"] for r in rows] == [1, 2] and all(r["machine_cpu_model"] == m["cpu_model"] for r in rows)


def test_cpu_steal_is_the_stolen_share_of_the_ticks_between_two_readings():
    before = (100, 0, 50, 800, 0, 0, 0, 50)
    after = (160, 0, 70, 840, 0, 0, 0, 130)  # 200 ticks: 60 user, 20 system, 40 idle, 80 stolen
    assert cpu_steal(before, after) == 0.4
    assert cpu_steal(before, before) is None  # no tick between: no figure
    assert cpu_steal(None, after) is None and cpu_steal(before, None) is None
    now = cpu_ticks()  # /proc/stat on Linux; None elsewhere
    assert now is None or (len(now) == 8 and all(v >= 0 for v in now))
