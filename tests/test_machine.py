"""Every bench result names its machine; the ISA is read from feature names, not guessed."""

from __future__ import annotations

import json

from dpmhw.cli.apps import write_json
from dpmhw.machine import _isa, avx2_features, machine_info


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
