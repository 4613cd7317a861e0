"""Mesh files are charged for what they decode to: bombs (a header declaring 10⁹ faces, a GLB
declaring a 4 GB buffer, archives expanding past the cap, an OBJ over the triangle budget) are
refused before the decode with a one-line reason naming the file, in bounded memory; a
Latin-1 comment loads."""

from __future__ import annotations

import bz2
import gzip
import io
import json
import struct
import tarfile
import tracemalloc
import zipfile

import numpy as np
import pytest

from dpmhw.mesh_limits import (
    BYTES_PER_TRIANGLE,
    BYTES_PER_VERTEX,
    PROCESS_BYTES,
    MeshCounts,
    MeshPart,
    budget_problem,
    count_mesh,
)
from dpmhw.meshes import load_mesh

TETRA = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def refused(path, *words):
    """The one-line ValueError load_mesh raises for `path`, checked to name the file and `words`."""
    with pytest.raises(ValueError) as info:
        load_mesh(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message
    for word in words:
        assert word in message, message
    assert not message.rstrip().endswith(":"), message  # a reason follows every colon
    return message


def grid_obj(n: int) -> str:
    """An n×n grid of quads as OBJ text: (n+1)² vertices, 2n² triangles."""
    lines = [f"v {i} {j} {(i * j) % 3}" for i in range(n + 1) for j in range(n + 1)]
    for i in range(n):
        for j in range(n):
            a = i * (n + 1) + j + 1
            lines.append(f"f {a} {a + n + 1} {a + n + 2} {a + 1}")
    return "\n".join(lines) + "\n"


def glb(tree: dict, binary: bytes = b"") -> bytes:
    body = json.dumps(tree).encode()
    body += b" " * (-len(body) % 4)
    chunks = struct.pack("<II", len(body), 0x4E4F534A) + body
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def triangle_glb(nodes: int = 1, **buffer) -> tuple[dict, bytes]:
    """One triangle (3 float32 positions, 3 uint16 indices), instanced by `nodes` nodes."""
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes()
    indices = np.array([0, 1, 2, 0], np.uint16).tobytes()
    tree = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(positions) + len(indices), **buffer}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0, "translation": [2.0 * i, 0, 0]} for i in range(nodes)],
        "scenes": [{"nodes": list(range(nodes))}],
        "scene": 0,
    }
    return tree, positions + indices


# ------------------------------------------------------------------ the bombs


def test_a_ply_header_declaring_a_billion_faces_is_refused_by_its_header(tmp_path):
    path = tmp_path / "bomb.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     b"property float z\nelement face 1000000000\nproperty list uchar int vertex_indices\nend_header\n"
                     + np.zeros(9, np.float32).tobytes() + b"\x03" + np.arange(3, dtype=np.int32).tobytes())
    refused(path, "1,000,000,000 face rows", "bytes")  # the rows it declares are not in the file


def test_a_ply_whose_declared_rows_are_present_is_charged_to_the_budget(tmp_path, monkeypatch):
    """A consistent file over the budget is refused by the budget, from the header alone."""
    path = tmp_path / "big.ply"
    faces = 20_000
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     b"property float z\nelement face %d\nproperty list uchar int vertex_indices\nend_header\n" % faces
                     + np.eye(3, dtype=np.float32).tobytes()
                     + (b"\x03" + np.arange(3, dtype=np.int32).tobytes()) * faces)
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "260")  # the process's 256 MiB and 8 MiB for the triangles
    refused(path, "20,000 triangles", "PLY header", "DPMHW_RENDER_MEMORY_MB")
    monkeypatch.delenv("DPMHW_RENDER_MEMORY_MB")
    assert len(load_mesh(path).faces) == faces  # within the default budget it loads


def test_a_glb_declaring_a_4_gb_buffer_names_the_buffer(tmp_path):
    tree, binary = triangle_glb()
    tree["buffers"][0]["byteLength"] = 4 * 2**30
    path = tmp_path / "bomb.glb"
    path.write_bytes(glb(tree, binary))
    refused(path, "buffers[0] declares 4,294,967,296 bytes", "BIN chunk holds 44")


def test_a_glb_accessor_without_data_declaring_a_billion_vertices_is_refused(tmp_path):
    tree, binary = triangle_glb()
    tree["accessors"][0] = {"componentType": 5126, "count": 10**9, "type": "VEC3"}  # zeros, allocated by count
    path = tmp_path / "zeros.glb"
    path.write_bytes(glb(tree, binary))
    refused(path, "decode to 11,444 MiB", "DPMHW_MAX_MESH_MB")


def test_a_glb_instancing_one_mesh_many_times_is_charged_per_instance(tmp_path, monkeypatch):
    tree, binary = triangle_glb(nodes=2000)
    path = tmp_path / "instanced.glb"
    path.write_bytes(glb(tree, binary))
    assert count_mesh(MeshPart(path.name, "glb", path.read_bytes())).triangles == 2000
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "257")  # 2,000 triangles and 6,000 vertices: 2 MiB over 256
    refused(path, "2,000 triangles", "nodes instancing")


def test_a_glb_node_cycle_is_refused(tmp_path):
    tree, binary = triangle_glb(nodes=2)
    tree["nodes"][0]["children"], tree["nodes"][1]["children"] = [1], [0]
    path = tmp_path / "cycle.glb"
    path.write_bytes(glb(tree, binary))
    refused(path, "cycle")


def test_a_draco_compressed_gltf_is_refused_by_name(tmp_path):
    tree, binary = triangle_glb()
    tree["extensionsRequired"] = ["KHR_draco_mesh_compression"]
    path = tmp_path / "draco.glb"
    path.write_bytes(glb(tree, binary))
    refused(path, "KHR_draco_mesh_compression")


def zeros_obj(size: int) -> bytes:
    """OBJ text that compresses about a thousandfold: one vertex line repeated."""
    return TETRA.encode() + b"v 0 0 0\n" * (size // 8)


@pytest.mark.parametrize("suffix", ["zip", "gz", "bz2", "tar.gz", "tar.bz2"])
def test_a_compressed_mesh_expanding_past_the_cap_is_refused_while_reading(tmp_path, monkeypatch, suffix):
    data = zeros_obj(3 * 2**20)
    path = tmp_path / f"bomb.{suffix}"
    if suffix == "zip":
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
            archive.writestr("bomb.obj", data)
    elif suffix in ("gz", "bz2"):
        path = tmp_path / f"bomb.obj.{suffix}"
        path.write_bytes(gzip.compress(data) if suffix == "gz" else bz2.compress(data))
    else:
        with tarfile.open(path, "w:" + suffix.split(".")[1]) as archive:
            info = tarfile.TarInfo("bomb.obj")
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    assert path.stat().st_size < 2**20 / 4  # under the file-size cap as stored
    monkeypatch.setenv("DPMHW_MAX_MESH_MB", "1")
    refused(path, "expands past 1 MiB", "DPMHW_MAX_MESH_MB")
    monkeypatch.setenv("DPMHW_MAX_MESH_MB", "8")
    assert len(load_mesh(path).faces) == 4  # within the cap the same file loads


def test_a_zip_listing_too_many_entries_is_refused_before_listing_them(tmp_path):
    path = tmp_path / "many.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("a.obj", TETRA)
    data = bytearray(path.read_bytes())
    at = data.rfind(b"PK\x05\x06")
    struct.pack_into("<HH", data, at + 8, 0xFFFF, 0xFFFF)  # entries on this disk, entries in all
    path.write_bytes(bytes(data))
    refused(path, "65,535 entries")


def test_an_obj_over_the_triangle_budget_is_refused_by_its_streaming_count(tmp_path, monkeypatch):
    path = tmp_path / "grid.obj"
    path.write_text(grid_obj(100))  # 10,201 vertices, 20,000 triangles (quads fan into two)
    need = (PROCESS_BYTES + 10_201 * BYTES_PER_VERTEX + 20_000 * BYTES_PER_TRIANGLE) / 2**20
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", str(int(need) - 1))
    message = refused(path, "20,000 triangles", "10,201 vertices", "counted in the OBJ", "DPMHW_RENDER_MEMORY_MB")
    assert f"about {need:,.0f} MiB" in message
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", str(int(need) + 1))
    mesh = load_mesh(path)
    assert len(mesh.faces) == 20_000 - mesh.dropped_degenerate


def test_the_default_budget_admits_the_bunny_and_refuses_a_ten_million_triangle_scan():
    """A 10M-triangle scan peaked at 4.65 GB loaded and rendered: over the default 4608 MiB."""
    assert budget_problem(MeshCounts(35_947, 69_451, "the Stanford bunny")) is None
    assert budget_problem(MeshCounts(2_000_000, 4_000_000, "a 4M-triangle scan")) is None
    assert "4,608 MiB" in budget_problem(MeshCounts(5_000_000, 9_990_000, "a 10M-triangle scan"))


def test_the_obj_count_matches_trimesh_across_chunk_boundaries(tmp_path, monkeypatch):
    """Counts equal what trimesh decodes, with lines cut at every chunk boundary."""
    from dpmhw import mesh_limits

    text = "# comment\n" + grid_obj(30).replace("\nf", "\r\nf\t") + "vn 0 1 0\nvt 0 0\nf 1 2 3 4 5\ng name\n"
    path = tmp_path / "grid.obj"
    path.write_text(text)
    monkeypatch.setattr(mesh_limits, "OBJ_CHUNK", 97)  # a prime, so boundaries fall everywhere
    counts = count_mesh(MeshPart(path.name, "obj", None, path=path))
    assert counts.triangles == 2 * 30 * 30 + 3
    assert counts.vertices == 31 * 31 + 2  # v rows, and the vn and vt rows trimesh also parses
    assert counts.other_bytes == len("# comment\n") + len("g name\n")


def test_an_obj_of_comments_is_charged_for_its_text(tmp_path, monkeypatch):
    """Comment lines decode to nothing but pass through trimesh's text handling (about three
    bytes per byte): a file of them is charged for that, not only for its four triangles."""
    path = tmp_path / "comments.obj"
    path.write_bytes(TETRA.encode() + (b"# " + b"x" * 1021 + b"\n") * 4096)  # 4 MiB of comments
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "265")  # 256 for the process, the comments need 14
    refused(path, "4 MiB of other text", "DPMHW_RENDER_MEMORY_MB")
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "271")
    assert len(load_mesh(path).faces) == 4


def test_an_ascii_and_a_binary_stl_and_an_off_are_counted_from_their_headers(tmp_path):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    for name, data in (("a.stl", trimesh.exchange.stl.export_stl_ascii(mesh).encode()),
                       ("b.stl", trimesh.exchange.stl.export_stl(mesh)),
                       ("c.off", trimesh.exchange.off.export_off(mesh).encode())):
        counts = count_mesh(MeshPart(name, name[-3:], data))
        assert counts.triangles == len(mesh.faces), name
        assert counts.other_bytes == (len(data) if name == "a.stl" else 0), name  # ASCII STL: its text is charged too
        (tmp_path / name).write_bytes(data)
        assert len(load_mesh(tmp_path / name).faces) == len(mesh.faces), name


def test_a_binary_stl_whose_count_does_not_match_its_size_is_refused(tmp_path):
    path = tmp_path / "liar.stl"
    path.write_bytes(b"\0" * 80 + struct.pack("<I", 10**9) + b"\0" * 50)
    refused(path, "84 + 50 per triangle")


def test_refusing_the_bombs_holds_little_memory(tmp_path, monkeypatch):
    """Peak traced allocation while refusing each bomb: headers are read alone, archives to the
    cap and no further, the OBJ count a MiB at a time. The bounds (a few MiB; 32 MiB for the
    OBJ's per-byte masks) are far below what the bombs would decode to (gigabytes; 900k
    triangles are about 400 MiB)."""
    monkeypatch.setenv("DPMHW_MAX_MESH_MB", "1")
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", "320")  # 900k triangles need about 620
    ply = tmp_path / "bomb.ply"
    ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    b"element face 1000000000\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    tree, binary = triangle_glb()
    tree["buffers"][0]["byteLength"] = 4 * 2**30
    glb_path = tmp_path / "bomb.glb"
    glb_path.write_bytes(glb(tree, binary))
    gz = tmp_path / "bomb.obj.gz"
    gz.write_bytes(gzip.compress(zeros_obj(64 * 2**20), compresslevel=1))
    obj = tmp_path / "big.obj"
    obj.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 900_000)  # 7 MB
    tracemalloc.start()
    try:
        for path, words in ((ply, "face rows"), (glb_path, "buffers[0]"), (gz, "expands past")):
            tracemalloc.reset_peak()
            refused(path, words)
            assert tracemalloc.get_traced_memory()[1] < 8 * 2**20, path
        monkeypatch.setenv("DPMHW_MAX_MESH_MB", "64")
        tracemalloc.reset_peak()
        refused(obj, "900,000 triangles")
        assert tracemalloc.get_traced_memory()[1] < 32 * 2**20, obj
    finally:
        tracemalloc.stop()


# ------------------------------------------------------------------ encodings and reasons


def test_an_obj_with_a_latin_1_comment_loads(tmp_path):
    path = tmp_path / "scan.obj"
    path.write_bytes("# café © 2003 Autodesk\n".encode("latin-1") + TETRA.encode())
    mesh = load_mesh(path)
    assert len(mesh.faces) == 4


def test_a_binary_ply_with_a_latin_1_header_comment_loads(tmp_path):
    import trimesh

    data = trimesh.exchange.ply.export_ply(trimesh.creation.icosphere(subdivisions=1), encoding="binary")
    path = tmp_path / "scan.ply"
    path.write_bytes(data.replace(b"format binary_little_endian 1.0\n",
                                  "format binary_little_endian 1.0\ncomment café © 2003 Autodesk\n".encode("latin-1")))
    assert len(load_mesh(path).faces) == 80


def test_a_utf8_obj_with_a_byte_order_mark_and_accents_loads(tmp_path):
    path = tmp_path / "scan.obj"
    path.write_bytes("\ufeff# café © 2003\n".encode("utf-8") + TETRA.encode())
    assert len(load_mesh(path).faces) == 4


def test_an_obj_with_a_latin_1_material_library_loads(tmp_path):
    """Its texture, without texture coordinates to apply it, is named and not read."""
    (tmp_path / "scan.mtl").write_bytes("# matériau ©\nnewmtl a\nmap_Kd missing.png\n".encode("latin-1"))
    path = tmp_path / "scan.obj"
    path.write_text("mtllib scan.mtl\nusemtl a\n" + TETRA)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 4 and any("missing.png" in note for note in mesh.notes)


@pytest.mark.parametrize("name, data, words", [
    ("empty.glb", b"", "12-byte header"),
    ("short.glb", struct.pack("<4sII", b"glTF", 2, 2**31) + b"\0" * 8, "declares 2,147,483,648 bytes"),
    ("text.glb", b"not a glb at all, just text", "GLB magic"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex many\nend_header\n", "PLY header line 3"),
    ("nohead.ply", b"ply\n" + b"comment x\n" * 10_000, "no 'end_header'"),
    ("bad.off", b"OFF\n3 lots 0\n", "OFF counts"),
    ("mesh.xyz", b"0 0 0\n", "unsupported mesh format .xyz"),
    ("values.gltf", b"[" + b"0," * 1_000_001 + b"0]", "1,000,002 values"),
    ("shape.gltf", b'{"buffers": 5}', "buffers is not a list"),
    ("broken.zip", b"PK\x03\x04 not really", "end-of-central-directory"),
    ("broken.obj.gz", b"\x1f\x8b\x08\x00 truncated", "cannot expand"),
    ("empty.zip", None, "holds no"),
    ("nothing.obj", b"# only a comment\n", "no triangles"),
])
def test_every_refusal_names_its_reason(tmp_path, name, data, words):
    path = tmp_path / name
    if data is None:
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("readme.txt", "no mesh here")
    else:
        path.write_bytes(data)
    refused(path, words)


def test_a_gltf_reads_only_the_buffer_files_it_names_and_counts_them(tmp_path):
    tree, binary = triangle_glb()
    tree["buffers"][0]["uri"] = "tri.bin"
    (tmp_path / "tri.bin").write_bytes(binary)
    path = tmp_path / "tri.gltf"
    path.write_text(json.dumps(tree))
    assert len(load_mesh(path).faces) == 1
    tree["buffers"][0]["uri"] = "missing.bin"
    path.write_text(json.dumps(tree))
    refused(path, "missing.bin", "not a file")


def test_a_glb_loads_with_its_node_transforms_and_a_zipped_gltf_with_its_buffer(tmp_path):
    tree, binary = triangle_glb(nodes=3)
    path = tmp_path / "three.glb"
    path.write_bytes(glb(tree, binary))
    mesh = load_mesh(path)
    assert len(mesh.faces) == 3 and mesh.vertices[:, 0].max() == pytest.approx(5.0)  # nodes at x = 0, 2, 4
    tree["buffers"][0]["uri"] = "tri.bin"
    archive_path = tmp_path / "tri.zip"
    with zipfile.ZipFile(archive_path, "w") as archive:
        archive.writestr("model/tri.gltf", json.dumps(tree))
        archive.writestr("model/tri.bin", binary)
    assert len(load_mesh(archive_path).faces) == 3


def test_mangled_headers_load_or_are_refused_in_one_line(tmp_path):
    """Seeded byte mutations of small files of each format: each loads, or raises a one-line
    ValueError naming the file; nothing else escapes (no KeyError, TypeError, empty reason)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1)
    tree, binary = triangle_glb(nodes=2)
    originals = {
        "m.obj": TETRA.encode(),
        "m.ply": trimesh.exchange.ply.export_ply(mesh, encoding="binary"),
        "a.ply": trimesh.exchange.ply.export_ply(mesh, encoding="ascii"),
        "m.stl": trimesh.exchange.stl.export_stl(mesh),
        "m.off": trimesh.exchange.off.export_off(mesh).encode(),
        "m.glb": glb(tree, binary),
        "j.glb": glb({**tree, "nodes": [{"mesh": [0]}, {"children": {"a": 1}}], "extensionsUsed": "x"}, binary),
    }
    rng = np.random.default_rng(33)
    outcomes = {"loaded": 0, "refused": 0}
    for name, data in originals.items():
        head = min(len(data), 400)  # the headers: where a count or a length is declared
        for trial in range(60):
            mutated = bytearray(data)
            for at in rng.integers(0, head, size=rng.integers(1, 4)):
                mutated[at] = int(rng.integers(0, 256))
            path = tmp_path / f"{trial}-{name}"
            path.write_bytes(bytes(mutated))
            try:
                load_mesh(path)
                outcomes["loaded"] += 1
            except ValueError as exc:
                message = str(exc)
                assert str(path) in message and "\n" not in message and not message.rstrip().endswith(":"), message
                outcomes["refused"] += 1
    assert min(outcomes.values()) > 20, outcomes  # else the mutations exercise only one side


def test_a_scene_whose_meshes_fit_alone_but_not_together_is_refused_before_decoding(tmp_path, monkeypatch):
    """Three grids, each within the budget, together over it: the scene is refused naming every
    file and the totals, and no mesh is decoded (trimesh is never asked)."""
    import trimesh

    from dpmhw.errors import SceneError
    from dpmhw.scene_file import load_scene

    for name in ("a", "b", "c"):
        (tmp_path / f"{name}.obj").write_text(grid_obj(100))  # 10,201 vertices, 20,000 triangles each
    one = (10_201 * BYTES_PER_VERTEX + 20_000 * BYTES_PER_TRIANGLE) / 2**20
    scene = tmp_path / "scene.toml"
    scene.write_text("""
[render]
width = 16
height = 12
background = [0.1, 0.1, 0.1]

[camera]
fx = 10.0
fy = 10.0
cx = 8.0
cy = 6.0
position = [0.0, 0.0, 2.0]
look_at = [0.0, 0.0, 0.0]
""" + "".join(f'\n[[objects]]\nshape = "mesh"\nmesh = "{n}.obj"\nsmooth = false\n' for n in "abc"))
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", str(int(256 + 2.5 * one)))  # room for two and a half
    decoded = []
    real_load = trimesh.load
    monkeypatch.setattr(trimesh, "load", lambda *a, **kw: decoded.append(1) or real_load(*a, **kw))
    with pytest.raises(SceneError) as info:
        load_scene(scene)
    message = str(info.value)
    assert "\n" not in message and decoded == []
    for name in ("a", "b", "c"):
        assert str(tmp_path / f"{name}.obj") in message
    assert "3 meshes together, 60,000 triangles and 30,603 vertices" in message
    assert f"about {256 + 3 * one:,.0f} MiB" in message and "DPMHW_RENDER_MEMORY_MB" in message
    monkeypatch.setenv("DPMHW_RENDER_MEMORY_MB", str(int(256 + 3 * one) + 1))  # all three fit
    assert len(load_scene(scene).objects) == 3 and len(decoded) == 3


def test_the_scene_budget_counts_the_built_in_bunny_and_quad_grids():
    from dpmhw.mesh_limits import scene_budget_problem

    bunny = MeshCounts(35_947, 69_451, "package data")
    grid = MeshCounts(1025 ** 2, 2 * 1024 ** 2, "grid")
    assert scene_budget_problem({"bunny": bunny, "quad": grid}) is None
    message = scene_budget_problem({"bunny": bunny, **{f"quad {i}": grid for i in range(5)}})
    assert message.startswith("the scene's 6 meshes together, 10,555,211 triangles") and "4,608 MiB" in message
