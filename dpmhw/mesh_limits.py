"""What a mesh file will decode to, read before anything decodes it, so that no file under the
limits makes the process allocate without bound.

A mesh is charged for what trimesh, `meshes.clean` and the renderer (triangle table, Embree BVH)
hold at their peak, not for the bytes it is stored in, against `DPMHW_RENDER_MEMORY_MB`
(default 4608, see `limits`):

- `BYTES_PER_TRIANGLE` and `BYTES_PER_VERTEX`: the peak RSS of `dpmhw render SCENE --spp 1` at
  64×48 (OBJ parse, clean, triangle rows, BVH, one pass) with a mesh of 0.2M, 1M and 2M
  triangles, its growth over the growth in triangles. A wavy grid OBJ with normals (one `v` and
  one `vn` row per triangle) grew 557, 585 and 607 bytes per triangle (0.2M→1M, 0.2M→2M,
  1M→2M; repeated runs within 1 %); the same triangles unshared (three `v` rows each, as STL
  stores them) 944, 939 and 934. Solved for the two costs: 360–445 bytes per triangle and
  163–194 per vertex row, taken as 450 and 200. OBJ text is the costliest decode; binary
  formats cost less.
- `BYTES_PER_OTHER_BYTE`: an OBJ's lines that decode to nothing (comments, names) still pass
  through trimesh's text handling: 200 MiB of comment lines raised the peak RSS of `load_mesh`
  by 613 MiB, 3.1 bytes per byte, taken as 3.5. ASCII PLY and STL carry more text per triangle
  than an OBJ (an ASCII STL about 200 bytes): all their data is charged at this rate too, on
  top of their rows (a 1M-triangle grid rendered as above peaked at 1,661 MiB from ASCII STL and
  844 MiB from ASCII PLY, charged 1,942 and 913).
- `PROCESS_BYTES`: that render's peak RSS with a 2-triangle mesh (interpreter, trimesh, the
  compiled kernels, the buffers of a small render): 247 MiB, taken as 256, so that a mesh at
  the budget and a small render together stay under the limit.
- What is counted before the decode: a PLY or OFF header's element counts, a binary STL's
  triangle count (an ASCII STL's `vertex` lines), a streaming count of an OBJ's `v`/`vt`/`vn`
  lines and of the triangles its `f` lines fan into (a MiB at a time), and a glTF's
  accessor counts times the nodes that instance each mesh. Declared sizes are checked against
  what is stored (a PLY's rows, a GLB's buffers and chunks), so a header cannot promise more
  than the file holds; the decoded arrays are checked again after the decode, before the BVH.
- Compressed files (.zip, .tar.gz, .tar.bz2, .gz, .bz2) are expanded here, through a reader
  that stops at `DPMHW_MAX_MESH_MB` of output; Draco or meshopt compressed glTF is refused
  (trimesh cannot decode it without optional packages).
- A mesh's base-colour texture (an OBJ's `map_Kd`, a PLY's `TextureFile`, a glTF's
  `baseColorTexture`, see `textures`) is charged `textures.BYTES_PER_TEXEL` per texel, its size
  read from the image's header before the decode; the image file is bounded by
  `DPMHW_MAX_MESH_MB` like the mesh.
- Text (an OBJ, a PLY header) is UTF-8, or Latin-1 where it is not (scanner software writes `©`
  and accented names into comments), re-encoded here rather than left to trimesh's optional
  charset guesser.

Every refusal is a `ValueError` of one line naming the file and the reason.
"""

from __future__ import annotations

import base64
import bz2
import codecs
import gzip
import io
import json
import posixpath
import re
import struct
import tarfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dpmhw.limits import check_file_size, max_mesh_bytes, render_memory_limit
from dpmhw.textures import BYTES_PER_TEXEL, Texture, decode_texture, open_texture, parse_mtl

__all__ = ["ARCHIVE_FORMATS", "BYTES_PER_OTHER_BYTE", "BYTES_PER_TRIANGLE", "BYTES_PER_VERTEX", "MESH_FORMATS",
           "PROCESS_BYTES", "DecodedMesh", "MeshCounts", "MeshPart", "budget_problem", "charge", "count_file",
           "count_mesh", "mesh_parts", "read_mesh", "scene_budget_problem"]

BYTES_PER_TRIANGLE = 450
BYTES_PER_VERTEX = 200
BYTES_PER_OTHER_BYTE = 3.5
PROCESS_BYTES = 256 << 20

MESH_FORMATS = ("obj", "ply", "stl", "off", "glb", "gltf")
ARCHIVE_FORMATS = ("zip", "tar.gz", "tar.bz2", "gz", "bz2")
MAX_ARCHIVE_MEMBERS = 10_000  # a zip's central directory or a tar's headers are held whole
MAX_ZIP_DIRECTORY = 4 << 20  # bytes of a zip's central directory (46 or more an entry)
MAX_JSON_VALUES = 1_000_000  # a glTF header names buffers, not vertices: a few thousand values
MAX_HEADER_BYTES = 1 << 16  # a PLY header, or the lines before an OFF's counts
CHUNK = 4 << 20  # bytes read at a time from a compressed stream or an ASCII STL
OBJ_CHUNK = 1 << 20  # an OBJ is counted a MiB at a time: about 20 bytes of masks and sums per byte


@dataclass
class MeshCounts:
    """What a mesh decodes to: `vertices` (rows of vertex data), `triangles`, where the counts
    were read, and `other_bytes` of text charged apart from the rows (an OBJ's comments, all of
    an ASCII PLY's or STL's data)."""

    vertices: int
    triangles: int
    how: str
    other_bytes: int = 0
    texels: int = 0

    def __add__(self, other: MeshCounts) -> MeshCounts:
        how = "; ".join(dict.fromkeys(self.how.split("; ") + other.how.split("; ")))  # each way of counting once
        return MeshCounts(self.vertices + other.vertices, self.triangles + other.triangles, how,
                          self.other_bytes + other.other_bytes, self.texels + other.texels)


@dataclass
class DecodedMesh:
    """A mesh file as decoded: vertices (V, 3), faces (F, 3), per-vertex texture coordinates uv
    (V, 2) with its base-colour texture (or both None), and notes naming what the file declares
    that the renderer does not model."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: Texture | None = None
    notes: list[str] = field(default_factory=list)


@dataclass
class MeshPart:
    """One mesh to decode: its format, its bytes (or None: read `path` from disk), and for a
    glTF the files its buffers name, already read."""

    name: str
    file_type: str
    data: bytes | None
    path: Path | None = None
    files: dict[str, bytes] | None = None
    latin_1: int = 0  # leading bytes of text that are Latin-1, not UTF-8 (the OBJ, the PLY header)
    sidecar: object = None  # name → bytes of a file beside it (an OBJ's MTL and images), or None when absent
    mtllibs: list[str] | None = None  # an OBJ's `mtllib` files and `usemtl` names, found by the count
    materials: set[str] | None = None
    has_vt: bool = False  # texture coordinates declared (an OBJ's vt lines, a PLY's properties)
    texture_name: str = ""  # a PLY's `comment TextureFile`, a glTF's base-colour image
    texture_data: bytes | None = None  # a glTF's base-colour image (a PLY's and an OBJ's are files beside it)
    notes: list[str] = field(default_factory=list)  # what the count found declared and not modelled

    def open(self):
        return io.BytesIO(self.data) if self.data is not None else open(self.path, "rb")


def file_type(name: str) -> str:
    """The format suffix of `name` (lower case, with the two-part tar suffixes)."""
    lower = name.lower()
    for double in ("tar.gz", "tar.bz2"):
        if lower.endswith("." + double):
            return double
    return lower.rsplit(".", 1)[-1] if "." in Path(lower).name else ""


# ------------------------------------------------------------------ budget

def charge(counts: MeshCounts) -> int:
    """Bytes a mesh of `counts` holds at its peak while it is loaded and traced (no process share)."""
    return (counts.vertices * BYTES_PER_VERTEX + counts.triangles * BYTES_PER_TRIANGLE
            + int(counts.other_bytes * BYTES_PER_OTHER_BYTE) + counts.texels * BYTES_PER_TEXEL)


def _over_limit(need: int) -> str:
    return (f"need about {need / 2**20:,.0f} MiB to load and trace ({BYTES_PER_TRIANGLE} bytes per triangle, "
            f"{BYTES_PER_VERTEX} per vertex, {PROCESS_BYTES >> 20} MiB for the process), over the render memory "
            f"limit of {render_memory_limit() / 2**20:,.0f} MiB (raise it with DPMHW_RENDER_MEMORY_MB)")


def budget_problem(counts: MeshCounts) -> str | None:
    """Why a mesh of `counts` would take too much memory to load and trace, or None when it fits."""
    need = PROCESS_BYTES + charge(counts)
    if need <= render_memory_limit():
        return None
    other = f" and {counts.other_bytes / 2**20:,.0f} MiB of other text" if counts.other_bytes >= 2**20 else ""
    other += f" and a texture of {counts.texels:,} texels ({BYTES_PER_TEXEL} bytes each)" if counts.texels else ""
    return f"{counts.triangles:,} triangles and {counts.vertices:,} vertices{other} ({counts.how}) {_over_limit(need)}"


def scene_budget_problem(meshes: dict[str, MeshCounts]) -> str | None:
    """Why the meshes of one scene (name → counts), all held at once, would take too much memory;
    None when they fit together. Names every mesh, largest first."""
    need = PROCESS_BYTES + sum(charge(c) for c in meshes.values())
    if need <= render_memory_limit():
        return None
    triangles = sum(c.triangles for c in meshes.values())
    vertices = sum(c.vertices for c in meshes.values())
    each = ", ".join(f"{name}: {c.triangles:,} triangles, {charge(c) / 2**20:,.0f} MiB"
                     for name, c in sorted(meshes.items(), key=lambda item: -charge(item[1])))
    return (f"the scene's {len(meshes)} meshes together, {triangles:,} triangles and {vertices:,} vertices ({each}), "
            f"{_over_limit(need)}")


# ------------------------------------------------------------------ compressed containers

class _CappedReader(io.RawIOBase):
    """A readable stream that raises once more than `cap` bytes have come out of `raw`."""

    def __init__(self, raw, cap: int, what: str):
        self.raw, self.cap, self.what, self.total = raw, cap, what, 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        data = self.raw.read(min(len(buffer), CHUNK))
        self.total += len(data)
        if self.total > self.cap:
            raise ValueError(f"{self.what} expands past {self.cap / 2**20:.3g} MiB (raise the limit with DPMHW_MAX_MESH_MB)")
        buffer[:len(data)] = data
        return len(data)


def _read_capped(stream, budget: list[int], what: str) -> bytes:
    """All of `stream`, charged to budget[0] (bytes left of the expansion cap); refuses beyond it."""
    out = io.BytesIO()
    while chunk := stream.read(min(CHUNK, budget[0] + 1)):  # never more than one byte past the cap
        budget[0] -= len(chunk)
        if budget[0] < 0:
            raise ValueError(f"{what} expands past {max_mesh_bytes() / 2**20:.3g} MiB "
                             f"(raise the limit with DPMHW_MAX_MESH_MB)")
        out.write(chunk)
    return out.getvalue()


def _check_zip_directory(path: Path) -> None:
    """Refuse a zip whose end-of-central-directory record declares too many entries or too
    large a directory, before zipfile lists them all (it reads the directory by its size)."""
    with open(path, "rb") as f:
        f.seek(0, io.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - (22 + 0xFFFF)))
        tail = f.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail):
        raise ValueError("not a zip archive (no end-of-central-directory record)")
    entries, directory = struct.unpack_from("<HI", tail, at + 10)
    if entries >= MAX_ARCHIVE_MEMBERS:
        raise ValueError(f"the archive lists {entries:,} entries, over {MAX_ARCHIVE_MEMBERS:,}")
    if directory > MAX_ZIP_DIRECTORY:
        raise ValueError(f"the archive's directory is {directory:,} bytes, over {MAX_ZIP_DIRECTORY:,}")


def _unpack(path: Path, kind: str) -> dict[str, bytes]:
    """The regular files in the archive or compressed file at `path`, at most DPMHW_MAX_MESH_MB in all."""
    budget = [max_mesh_bytes()]
    if kind == "zip":
        _check_zip_directory(path)
        files = {}
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if not info.is_dir():
                    with archive.open(info) as member:
                        files[info.filename] = _read_capped(member, budget, f"member {info.filename}")
        return files
    with open(path, "rb") as raw, (gzip.GzipFile(fileobj=raw) if kind.endswith("gz") else bz2.BZ2File(raw)) as stream:
        if not kind.startswith("tar"):  # one compressed file: its name without the suffix
            inner = path.name[: -len(kind) - 1]
            return {inner: _read_capped(stream, budget, "the compressed file")}
        capped = io.BufferedReader(_CappedReader(stream, budget[0], "the compressed archive"))
        files = {}
        with tarfile.open(fileobj=capped, mode="r|") as archive:  # stream mode: headers read as they come
            for count, info in enumerate(archive, 1):
                if count > MAX_ARCHIVE_MEMBERS:
                    raise ValueError(f"the archive has over {MAX_ARCHIVE_MEMBERS:,} entries")
                if info.isfile():
                    files[info.name] = archive.extractfile(info).read()
        return files


def mesh_parts(path: Path) -> list[MeshPart]:
    """The meshes in the file at `path` (its size already checked): itself, or the mesh files
    inside an archive (expanded here, bounded). Raises ValueError for an unsupported format or
    an archive without a mesh."""
    kind = file_type(path.name)
    if kind in MESH_FORMATS:
        part = MeshPart(path.name, kind, None, path=path, sidecar=lambda uri: _file_beside(path.parent, uri, "file"))
        if kind == "gltf":
            part.data = path.read_bytes()
            part.files = _gltf_sidecars(part.data, lambda uri: _file_beside(path.parent, uri, "glTF's buffer file"))
        return [part]
    if kind not in ARCHIVE_FORMATS:
        raise ValueError(f"unsupported mesh format {'.' + kind if kind else '(no suffix)'}: expected "
                         f"{', '.join('.' + k for k in MESH_FORMATS + ARCHIVE_FORMATS)}")
    try:
        files = _unpack(path, kind)
    except ValueError:
        raise
    except Exception as exc:  # zipfile, tarfile, gzip and bz2 raise many types for broken archives
        raise ValueError(f"cannot expand the {kind} file: {describe(exc)}") from exc
    parts = []
    for name, data in files.items():
        if file_type(name) in MESH_FORMATS:
            folder = posixpath.dirname(name)
            beside = lambda uri, folder=folder: files.get(posixpath.normpath(posixpath.join(folder, uri)))  # noqa: E731
            part = MeshPart(name, file_type(name), data, sidecar=beside)
            if part.file_type == "gltf":
                part.files = _gltf_sidecars(data, beside)
            parts.append(part)
    if not parts:
        raise ValueError(f"the {kind} file holds no {'/'.join(MESH_FORMATS)} mesh (it holds {len(files)} files)")
    return parts


def count_file(path: Path) -> tuple[list[MeshPart], MeshCounts]:
    """The meshes in the file at `path` (its size already checked) and what they decode to
    together, with an albedo texture's texels, counted before anything decodes them. Raises
    ValueError with the reason."""
    parts = mesh_parts(path)
    total = None
    for part in parts:
        try:
            counts = count_mesh(part)
        except ValueError as exc:
            raise ValueError(_member(parts, part) + describe(exc)) from None
        except Exception as exc:  # a header of the right syntax and the wrong shape (a list for a number, ...)
            raise ValueError(f"{_member(parts, part)}the {part.file_type.upper()} header is malformed: "
                             f"{type(exc).__name__}: {describe(exc)}") from exc
        total = counts if total is None else total + counts
    images = [(image, name) for image, name, _ in (_surface(part) for part in parts) if image is not None]
    if images and len(parts) > 1:
        raise ValueError(f"texture {images[0][1]}: a texture is rendered on a single mesh file, not on one of "
                         f"{len(parts)} meshes in an archive")
    total.texels = sum(image.size[0] * image.size[1] for image, _ in images)
    return parts, total


def read_mesh(path: Path) -> DecodedMesh:
    """The mesh file at `path`, all its meshes concatenated, each counted and charged to the
    budget (with an OBJ's texture) before trimesh decodes it. Raises ValueError with the reason."""
    parts, total = count_file(path)
    surfaces = [_surface(part) for part in parts]
    images = [(image, name) for image, name, _ in surfaces if image is not None]
    if problem := budget_problem(total):
        raise ValueError(problem)
    import trimesh

    meshes = []
    for part, (image, _, _) in zip(parts, surfaces):
        resolver = trimesh.resolvers.ZipResolver(part.files) if part.files else None
        try:
            with io.BytesIO(_latin_1_as_utf8(part)) if part.latin_1 else part.open() as f:
                # a glTF's texture coordinates come with its materials (their images opened lazily, charged above)
                materials = part.file_type in ("glb", "gltf") and image is not None
                meshes.append(trimesh.load(f, file_type=part.file_type, resolver=resolver, force="mesh", process=False,
                                           skip_materials=not materials))
        except Exception as exc:  # trimesh raises many types for broken files
            raise ValueError(f"{_member(parts, part)}trimesh cannot decode the {part.file_type.upper()} data: "
                             f"{describe(exc)}") from exc
    vertices = sum(len(m.vertices) for m in meshes)
    faces = sum(len(m.faces) for m in meshes)
    if problem := budget_problem(MeshCounts(vertices, faces, "as decoded", texels=total.texels)):
        raise ValueError(problem)
    notes = [_member(parts, part) + note for part in parts for note in part.notes]
    notes += [note for _, _, more in surfaces for note in more]
    notes += [f"{_member(parts, part)}vertex colours (not modelled: the scene's albedo is)"
              for part, m in zip(parts, meshes) if getattr(m.visual, "kind", None) in ("vertex", "face")]
    if len(meshes) == 1:
        decoded = DecodedMesh(np.asarray(meshes[0].vertices), np.asarray(meshes[0].faces), notes=notes)
        if images:
            decoded.uv, decoded.texture = _texture(meshes[0], *images[0], notes)
        return decoded
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return DecodedMesh(np.concatenate([np.asarray(m.vertices) for m in meshes]),
                       np.concatenate([np.asarray(m.faces) + o for m, o in zip(meshes, offsets)]), notes=notes)


def _surface(part: MeshPart) -> tuple[object, str, list[str]]:
    """(the base-colour image, lazily opened, or None; its name; notes) of a mesh: an OBJ's
    materials' `map_Kd`, a PLY's `TextureFile`, a glTF's `baseColorTexture`. An image declared
    and unreadable is an error naming it."""
    if part.file_type == "obj":
        name, notes = _obj_texture_name(part)
    else:
        name, notes = part.texture_name, []
    if not name:
        return None, "", notes
    if not part.has_vt:
        notes.append(f"texture {name} is not applied: the mesh has no texture coordinates")
        return None, "", notes
    data = part.texture_data if part.file_type in ("glb", "gltf") else part.sidecar(name)
    if data is None:
        raise ValueError(f"texture {name} of {part.name} is not a file beside it")
    from PIL import UnidentifiedImageError

    try:
        return open_texture(data), name, notes
    except UnidentifiedImageError:
        raise ValueError(f"cannot read texture {name}: not an image format Pillow reads (PNG, JPEG, …)") from None
    except Exception as exc:  # Pillow raises many types for broken images
        raise ValueError(f"cannot read texture {name}: {describe(exc)}") from None


def _obj_texture_name(part: MeshPart) -> tuple[str, list[str]]:
    """(the `map_Kd` of the materials an OBJ uses, from the MTL files beside it, or ""; notes).
    One image per mesh."""
    maps: dict[str, str] = {}
    ignored: list[str] = []
    notes = []
    for library in part.mtllibs or []:
        data = part.sidecar(library)
        if data is None:
            notes.append(f"material library {library} is not a file beside it: its materials are ignored")
            continue
        found, unmodelled = parse_mtl(_decode(data), part.materials or None)
        maps.update(found)
        ignored += [u for u in unmodelled if u not in ignored]
    if ignored:
        notes.append(f"its materials declare {', '.join(ignored)}: not modelled, ignored")
    names = sorted(set(maps.values()))
    if len(names) > 1:
        raise ValueError(f"the materials of {part.name} use {len(names)} map_Kd textures ({', '.join(names[:3])}"
                         f"{', …' if len(names) > 3 else ''}): one texture per mesh is rendered (bake them into one)")
    return (names[0] if names else ""), notes


def _texture(mesh, image, name: str, notes: list[str]) -> tuple[np.ndarray | None, Texture | None]:
    """(per-vertex uv, decoded texture) of a decoded mesh whose file names `image`; (None, None)
    with a note when the mesh has no texture coordinate for every vertex."""
    uv = getattr(mesh.visual, "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        notes.append(f"texture {name} is not applied: the mesh has no texture coordinates for every face")
        return None, None
    uv = np.asarray(uv, np.float64)
    if not np.all(np.abs(uv) <= MAX_TEXTURE_COORDINATE):  # NaN fails too
        raise ValueError(f"the mesh has texture coordinates that are non-finite or beyond ±{MAX_TEXTURE_COORDINATE:g}")
    try:
        texture, more = decode_texture(image, name)
    except Exception as exc:  # Pillow raises many types for a truncated or corrupt image
        raise ValueError(f"cannot read texture {name}: {describe(exc)}") from None
    notes += more
    return uv, texture


def _member(parts: list[MeshPart], part: MeshPart) -> str:
    return f"member {part.name}: " if part.path is None else ""


def _file_beside(folder: Path, uri: str, what: str) -> bytes | None:
    target = folder / uri
    if not target.is_file():
        return None
    check_file_size(target, max_mesh_bytes(), f"the {what}", "DPMHW_MAX_MESH_MB")
    return target.read_bytes()


def describe(exc: BaseException) -> str:
    """An exception as one line; its type where its message is empty."""
    text = " ".join(str(exc).split())
    return text if text else f"{type(exc).__name__} (no message)"


# ------------------------------------------------------------------ counting

def count_mesh(part: MeshPart) -> MeshCounts:
    """What `part` decodes to, from its header or a streaming count; checks that declared sizes
    fit what is stored. Sets `part.latin_1` where text is not UTF-8."""
    with part.open() as f:
        size = f.seek(0, io.SEEK_END)
        f.seek(0)
        return _COUNTERS[part.file_type](f, size, part)


def _count_obj(f, size: int, part: MeshPart) -> MeshCounts:
    """Streaming count of vertex rows (v, vt, vn) and of the triangles each `f` line fans into
    (k corners: k − 2), OBJ_CHUNK at a time; also decides the text encoding."""
    decoder = codecs.getincrementaldecoder("utf-8")()
    utf8 = True
    vertices = triangles = other = 0
    carry = b""
    part.mtllibs, part.materials = [], set()
    while True:
        chunk = f.read(OBJ_CHUNK)
        if utf8:
            try:
                decoder.decode(chunk, final=not chunk)
            except UnicodeDecodeError:
                utf8 = False
        text = carry + chunk
        if not chunk:
            if text:
                text += b"\n"
        else:
            cut = text.rfind(b"\n") + 1
            text, carry = text[:cut], text[cut:]
            if len(carry) > OBJ_CHUNK:
                raise ValueError(f"a line is over {OBJ_CHUNK >> 20} MiB long: not an OBJ file")
        if text:
            _obj_materials(text, part)
            v, t, o = _count_obj_lines(np.frombuffer(text, np.uint8))
            vertices += v
            triangles += t
            other += o
        if not chunk:
            break
    part.latin_1 = 0 if utf8 else size
    return MeshCounts(vertices, triangles, "counted in the OBJ's v/vt/vn and f lines", other)


_MATERIAL_LINE = re.compile(rb"^[ \t]*(mtllib|usemtl)[ \t]+([^\r\n#]*)", re.MULTILINE)
MAX_MATERIAL_NAMES = 10_000
MAX_TEXTURE_COORDINATE = 1e6  # in repeats; beyond is a wrong file (float32 keeps 1/16 of a repeat at 1e6)


_VT_LINE = re.compile(rb"^vt[ \t]", re.MULTILINE)


def _obj_materials(text: bytes, part: MeshPart) -> None:
    """The `mtllib` files and `usemtl` names in whole lines `text`, added to `part`'s, and
    whether it has a `vt` line."""
    part.has_vt = part.has_vt or _VT_LINE.search(text) is not None
    for key, value in _MATERIAL_LINE.findall(text):
        name = value.decode("utf-8", "replace").strip()
        if key == b"mtllib":
            part.mtllibs += [n for n in [name] if n and n not in part.mtllibs]
        else:
            part.materials.add(name)
        if len(part.mtllibs) + len(part.materials) > MAX_MATERIAL_NAMES:
            raise ValueError(f"the OBJ names over {MAX_MATERIAL_NAMES:,} materials")


def _count_obj_lines(a: np.ndarray) -> tuple[int, int, int]:
    """(vertex rows, triangles, bytes of other lines) in whole lines `a` (ending in a newline)."""
    space = (a == 32) | (a == 9) | (a == 13) | (a == 10)
    ends = np.flatnonzero(a == 10)
    starts = np.concatenate(([0], ends[:-1] + 1))
    first = a[starts]
    second = a[np.minimum(starts + 1, len(a) - 1)]
    blank = space[np.minimum(starts + 1, len(a) - 1)]
    blank_after_two = space[np.minimum(starts + 2, len(a) - 1)]
    vertex = (first == ord("v")) & (blank | (((second == ord("t")) | (second == ord("n"))) & blank_after_two))
    face = (first == ord("f")) & blank
    other = int((ends - starts + 1)[~(vertex | face)].sum())
    if not face.any():
        return int(vertex.sum()), 0, other
    token = ~space
    token[1:] &= space[:-1]  # a token starts where a non-space follows a space
    before = np.concatenate(([0], np.cumsum(token, dtype=np.int32)))
    tokens = before[ends + 1] - before[starts]  # tokens on each line, the keyword included
    return int(vertex.sum()), int(np.maximum(tokens[face] - 3, 0).sum()), other


_PLY_TYPES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _header_lines(f, end: bytes, what: str) -> tuple[list[str], int]:
    head = f.read(MAX_HEADER_BYTES)
    at = head.find(end)
    if at < 0:
        raise ValueError(f"no {end.decode().strip()!r} in the first {MAX_HEADER_BYTES >> 10} KiB: not a {what} file, or a broken header")
    stop = at + len(end)
    return head[:stop].decode("latin-1").splitlines(), stop


def _count_ply(f, size: int, part: MeshPart) -> MeshCounts:
    """The PLY header's element counts; each element's rows must fit in the bytes after the header
    (binary: the smallest row, lists at their shortest; ASCII: two bytes a value)."""
    lines, start = _header_lines(f, b"end_header", "PLY")
    f.seek(0)
    try:
        f.read(start).decode("utf-8")
    except UnicodeDecodeError:
        part.latin_1 = start
    if not lines or lines[0].strip() != "ply":
        raise ValueError("no 'ply' magic line")
    fmt = None
    elements: list[list] = []  # [name, count, min row bytes, values per row]
    for number, line in enumerate(lines[1:], 2):
        words = line.split()
        if words[:2] == ["comment", "TextureFile"]:
            part.texture_name = " ".join(words[2:])
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                count = int(words[2])
                if count < 0:
                    raise ValueError
                elements.append([words[1], count, 0, 0])
            elif words[0] == "property" and elements:
                element = elements[-1]
                if words[1] == "list":
                    least = 3 if element[0] == "face" else 0  # a face has three corners or more
                    element[2] += _PLY_TYPES[words[2]] + least * _PLY_TYPES[words[3]]
                    element[3] += 1 + least
                else:
                    element[2] += _PLY_TYPES[words[1]]
                    element[3] += 1
                # texture coordinates: a face's `texcoord` list, or per vertex (the names trimesh reads)
                part.has_vt |= words[-1] in ("texcoord", "texture_u", "u", "s")
            else:
                raise ValueError
        except (ValueError, IndexError, KeyError):
            raise ValueError(f"PLY header line {number} {line.strip()[:80]!r} is not understood") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"PLY format {fmt!r}: expected ascii, binary_little_endian or binary_big_endian")
    stored = size - start
    least = sum(count * (row if fmt != "ascii" else 2 * values) for _, count, row, values in elements)
    if least > stored:
        name, count = max(((e[0], e[1]) for e in elements), key=lambda e: e[1])
        raise ValueError(f"the PLY header declares {count:,} {name} rows (and others) needing at least {least:,} bytes, "
                         f"but {stored:,} follow the header")
    counts = {e[0]: e[1] for e in elements}
    return MeshCounts(counts.get("vertex", 0), counts.get("face", 0), "declared in the PLY header",
                      stored if fmt == "ascii" else 0)


def _count_off(f, size: int, part: MeshPart) -> MeshCounts:
    head = f.read(MAX_HEADER_BYTES).decode("latin-1")
    words = [w for line in head.splitlines() for w in line.split("#", 1)[0].split()][:4]
    if not words or not words[0].endswith("OFF"):
        raise ValueError("no OFF magic word")
    try:
        vertices, faces = int(words[1]), int(words[2])
        if vertices < 0 or faces < 0 or 2 * (3 * vertices + 4 * faces) > size:  # two bytes a value at least
            raise ValueError
    except (ValueError, IndexError):
        raise ValueError(f"the OFF counts {' '.join(words[1:4])!r} are not two non-negative whole numbers that fit the "
                         f"file's {size:,} bytes") from None
    return MeshCounts(vertices, faces, "declared in the OFF header")


def _count_stl(f, size: int, part: MeshPart) -> MeshCounts:
    """Binary: the count after the 80-byte header, 50 bytes a triangle; ASCII: its `vertex` words / 3."""
    head = f.read(84)
    if len(head) == 84:
        count = struct.unpack_from("<I", head, 80)[0]
        if 84 + 50 * count == size:
            return MeshCounts(3 * count, count, "declared in the binary STL header")
    if not head.lstrip().lower().startswith(b"solid"):
        raise ValueError(f"a binary STL of {size:,} bytes must be 84 + 50 per triangle, and an ASCII one starts with 'solid'")
    f.seek(0)
    words, carry = 0, b""
    while chunk := f.read(CHUNK):
        text = (carry + chunk).lower()
        words += text.count(b"vertex")
        carry = text[-5:]  # shorter than the word: a word split across chunks is counted once
    return MeshCounts(words, words // 3, "counted in the ASCII STL's vertex lines", size)


def _count_gltf(f, size: int, part: MeshPart) -> MeshCounts:
    data = f.read()
    if part.file_type == "glb":
        tree, buffers = _glb_chunks(data)
    else:
        tree, buffers = _json(data, "glTF"), []
    counts = _count_gltf_tree(tree, buffers, part.files or {})
    _gltf_surface(tree, data, part)
    return counts


def _gltf_surface(tree: dict, data: bytes, part: MeshPart) -> None:
    """The base-colour image of the materials a glTF's primitives use (its bytes and name into
    `part`, one image per mesh), whether those primitives have texture coordinates, and notes
    naming the other textures and factors, which are not modelled."""
    used = set()
    for mesh in _items(tree, "meshes"):
        for primitive in (mesh.get("primitives", []) if isinstance(mesh, dict) else []):
            if isinstance(primitive, dict) and "material" in primitive:
                used.add(primitive["material"])
                part.has_vt |= "TEXCOORD_0" in primitive.get("attributes", {})
    materials = _items(tree, "materials")
    images, ignored = set(), set()
    for index in sorted(m for m in used if isinstance(m, int) and 0 <= m < len(materials)):
        material = materials[index] if isinstance(materials[index], dict) else {}
        pbr = material.get("pbrMetallicRoughness", {})
        pbr = pbr if isinstance(pbr, dict) else {}
        ignored.update(k for k in [*pbr, *material] if k.endswith("Texture") and k != "baseColorTexture")
        factor = pbr.get("baseColorFactor", [1, 1, 1, 1])
        if factor != [1, 1, 1, 1]:
            ignored.add(f"baseColorFactor {factor} (the scene's albedo multiplies the texture)")
        if "baseColorTexture" in pbr:
            texture = _whole(pbr["baseColorTexture"], "index", f"materials[{index}].pbrMetallicRoughness.baseColorTexture")
            textures = _items(tree, "textures")
            if texture >= len(textures):
                raise ValueError(f"materials[{index}]'s baseColorTexture names textures[{texture}], which does not exist")
            images.add(_whole(textures[texture], "source", f"textures[{texture}]"))
    if ignored:
        part.notes.append(f"its materials declare {', '.join(sorted(ignored))}: not modelled, ignored")
    if len(images) > 1:
        raise ValueError(f"the materials its primitives use have {len(images)} base-colour images: one texture per mesh "
                         "is rendered (bake them into one)")
    if images:
        part.texture_name, part.texture_data = _gltf_image(tree, data, part, images.pop())


def _gltf_image(tree: dict, data: bytes, part: MeshPart, index: int) -> tuple[str, bytes | None]:
    """(name, bytes) of a glTF's images[index]: from a buffer view, a data URI or a file beside it
    (None when that file is missing)."""
    images = _items(tree, "images")
    if index >= len(images) or not isinstance(images[index], dict):
        raise ValueError(f"images[{index}] does not exist")
    image = images[index]
    if "uri" in image:
        uri = str(image["uri"])
        if uri.startswith("data:"):
            return f"images[{index}] (a data URI)", base64.b64decode(uri.partition(",")[2])
        return uri, part.sidecar(uri)
    view = _items(tree, "bufferViews")[_whole(image, "bufferView", f"images[{index}]")]
    buffer = _items(tree, "buffers")[_whole(view, "buffer", "the image's bufferView")]
    uri = buffer.get("uri")
    if uri is None:  # the GLB's BIN chunk, after the 12-byte header and the JSON chunk
        json_length = struct.unpack_from("<I", data, 12)[0]
        stored = data[12 + 8 + json_length + 8:]
    elif uri.startswith("data:"):
        stored = base64.b64decode(uri.partition(",")[2])
    else:
        stored = part.files[uri]
    start = view.get("byteOffset", 0)
    return f"images[{index}] (in buffer {view['buffer']})", stored[start:start + view["byteLength"]]


def _glb_chunks(data: bytes) -> tuple[dict, list[int]]:
    """The GLB's JSON and the lengths of its BIN chunks; every length checked against the bytes present."""
    if len(data) < 20:
        raise ValueError(f"a GLB file needs a 12-byte header and a chunk, this one is {len(data)} bytes")
    magic, version, length = struct.unpack_from("<4sII", data)
    if magic != b"glTF":
        raise ValueError(f"GLB magic {magic!r}: expected b'glTF'")
    if version != 2:
        raise ValueError(f"GLB version {version}: only glTF 2 is read")
    if length > len(data):
        raise ValueError(f"the GLB header declares {length:,} bytes, the file has {len(data):,}")
    at, tree, bins = 12, None, []
    while at + 8 <= length:
        chunk_length, kind = struct.unpack_from("<II", data, at)
        if at + 8 + chunk_length > length:
            raise ValueError(f"a GLB chunk at byte {at} declares {chunk_length:,} bytes, {length - at - 8:,} follow it")
        if tree is None:
            if kind != 0x4E4F534A:
                raise ValueError("the GLB's first chunk is not JSON")
            tree = _json(data[at + 8: at + 8 + chunk_length], "GLB JSON chunk")
        elif kind == 0x004E4942:
            bins.append(chunk_length)
        at += 8 + chunk_length
    if tree is None:
        raise ValueError("the GLB has no JSON chunk")
    return tree, bins


def _json(data: bytes, what: str) -> dict:
    values = data.count(b",") + data.count(b":") + data.count(b"[") + data.count(b"{")
    if values > MAX_JSON_VALUES:
        raise ValueError(f"the {what} has about {values:,} values, over {MAX_JSON_VALUES:,}")
    try:
        tree = json.loads(_decode(data))
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"the {what} is not JSON: {describe(exc)}") from None
    if not isinstance(tree, dict):
        raise ValueError(f"the {what} is not a JSON object")  # noqa: TRY004
    return tree


def _gltf_sidecars(data: bytes, lookup) -> dict[str, bytes]:
    """The files a glTF's buffers name, from `lookup(uri)` (bytes, or None when absent),
    DPMHW_MAX_MESH_MB in all; trimesh is given only these, so it reads no other path."""
    tree = _json(data, "glTF")
    budget = max_mesh_bytes()
    files = {}
    for i, buffer in enumerate(_items(tree, "buffers")):
        uri = buffer.get("uri") if isinstance(buffer, dict) else None
        if not isinstance(uri, str) or uri.startswith("data:") or uri in files:
            continue
        found = lookup(uri)
        if found is None:
            raise ValueError(f"buffers[{i}].uri {uri[:80]!r} is not a file beside the glTF")
        budget -= len(found)
        if budget < 0:
            raise ValueError(f"the glTF's buffer files are over {max_mesh_bytes() / 2**20:.3g} MiB "
                             f"(raise the limit with DPMHW_MAX_MESH_MB)")
        files[uri] = found
    return files


_GLTF_COMPONENTS = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_GLTF_TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLTF_COMPRESSION = ("KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression")


def _whole(table: dict, key: str, where: str, default: int | None = None, least: int = 0) -> int:
    value = table.get(key, default) if isinstance(table, dict) else None
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ValueError(f"{where}.{key} is {value!r}: expected a whole number ≥ {least}")
    return value


def _items(tree: dict, key: str) -> list:
    value = tree.get(key, [])
    if not isinstance(value, list):
        raise ValueError(f"glTF {key} is not a list")  # noqa: TRY004
    return value


def _count_gltf_tree(tree: dict, bin_chunks: list[int], files: dict[str, bytes]) -> MeshCounts:
    """Vertices and triangles as trimesh will decode them: every accessor decoded (bounded by
    DPMHW_MAX_MESH_MB in all), each mesh once per node path that instances it."""
    used = [e for e in _items(tree, "extensionsUsed") + _items(tree, "extensionsRequired") if e in _GLTF_COMPRESSION]
    if used:
        raise ValueError(f"compressed glTF ({used[0]}) cannot be decoded without optional packages: export it uncompressed")
    stored = []
    for i, buffer in enumerate(_items(tree, "buffers")):
        declared = _whole(buffer, "byteLength", f"buffers[{i}]")
        uri = buffer.get("uri")
        if uri is None:
            have, where = (bin_chunks[0] if bin_chunks else 0), "the GLB's BIN chunk"
        elif isinstance(uri, str) and uri.startswith("data:"):
            have, where = len(uri.partition(",")[2]) * 3 // 4, "its data URI"
        elif isinstance(uri, str) and uri in files:
            have, where = len(files[uri]), f"the file {uri!r}"
        else:
            raise ValueError(f"buffers[{i}].uri {str(uri)[:80]!r} names no data this file carries")
        if declared > have:
            raise ValueError(f"buffers[{i}] declares {declared:,} bytes, {where} holds {have:,}")
        stored.append(declared)
    cap = max_mesh_bytes()
    views = _items(tree, "bufferViews")
    total = 0
    for i, view in enumerate(views):
        buffer = _whole(view, "buffer", f"bufferViews[{i}]")
        start, length = _whole(view, "byteOffset", f"bufferViews[{i}]", 0), _whole(view, "byteLength", f"bufferViews[{i}]")
        if buffer >= len(stored) or start + length > stored[buffer]:
            raise ValueError(f"bufferViews[{i}] reaches byte {start + length:,} of buffer {buffer}, "
                             f"which {'does not exist' if buffer >= len(stored) else f'has {stored[buffer]:,}'}")
        total += length  # trimesh copies each view
    accessors = _items(tree, "accessors")
    for i, accessor in enumerate(accessors):
        where = f"accessors[{i}]"
        count = _whole(accessor, "count", where)
        component = _GLTF_COMPONENTS.get(accessor.get("componentType"))
        width = _GLTF_TYPES.get(accessor.get("type"))
        if component is None or width is None:
            raise ValueError(f"{where} has componentType {accessor.get('componentType')!r} / type {accessor.get('type')!r}")
        row = component * width
        total += count * row
        if "bufferView" in accessor:
            view_index = _whole(accessor, "bufferView", where)
            if view_index >= len(views):
                raise ValueError(f"{where}.bufferView {view_index} does not exist")
            view = views[view_index]
            stride = _whole(view, "byteStride", f"bufferViews[{view_index}]", row, least=1)
            end = _whole(accessor, "byteOffset", where, 0) + (max(count - 1, 0) * stride + row if count else 0)
            if end > view["byteLength"]:
                raise ValueError(f"{where} reads {end:,} bytes of bufferViews[{view_index}], which has {view['byteLength']:,}")
    if total > cap:
        raise ValueError(f"the glTF's buffer views and accessors decode to {total / 2**20:,.0f} MiB, over "
                         f"{cap / 2**20:.3g} MiB (raise the limit with DPMHW_MAX_MESH_MB)")
    per_mesh = []
    for i, mesh in enumerate(_items(tree, "meshes")):
        vertices = triangles = 0
        for j, primitive in enumerate(mesh.get("primitives", []) if isinstance(mesh, dict) else []):
            where = f"meshes[{i}].primitives[{j}]"
            attributes = primitive.get("attributes", {}) if isinstance(primitive, dict) else {}
            mode = _whole(primitive, "mode", where, 4)
            position = attributes.get("POSITION") if isinstance(attributes, dict) else None
            if position is None:
                continue
            corners = _accessor_count(accessors, position, f"{where}.attributes.POSITION")
            if "indices" in primitive:
                corners = _accessor_count(accessors, primitive["indices"], f"{where}.indices")
            vertices += _accessor_count(accessors, position, f"{where}.attributes.POSITION")
            triangles += corners // 3 if mode == 4 else max(corners - 2, 0) if mode in (5, 6) else 0
        per_mesh.append((vertices, triangles))
    instances = _instances(tree, len(per_mesh))
    vertices = sum(n * per_mesh[m][0] for m, n in instances.items())
    triangles = sum(n * per_mesh[m][1] for m, n in instances.items())
    return MeshCounts(vertices, triangles, "declared in the glTF accessors, times the nodes instancing each mesh")


def _accessor_count(accessors: list, index, where: str) -> int:
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(accessors):
        raise ValueError(f"{where} is {index!r}: not one of the {len(accessors)} accessors")
    return accessors[index]["count"]


def _instances(tree: dict, meshes: int) -> dict[int, int]:
    """mesh index → how many node paths reach it (trimesh copies a mesh per path). Roots: every
    scene's nodes, else the nodes no other node lists as a child; a cycle is refused."""
    nodes = _items(tree, "nodes")
    parents: list[list[int]] = [[] for _ in nodes]
    for i, node in enumerate(nodes):
        for child in (node.get("children", []) if isinstance(node, dict) else []):
            if isinstance(child, bool) or not isinstance(child, int) or not 0 <= child < len(nodes):
                raise ValueError(f"nodes[{i}].children names {child!r}: not one of the {len(nodes)} nodes")
            parents[child].append(i)
    roots = [0] * len(nodes)
    scenes = _items(tree, "scenes")
    for s, scene in enumerate(scenes):
        for root in (scene.get("nodes", []) if isinstance(scene, dict) else []):
            if isinstance(root, bool) or not isinstance(root, int) or not 0 <= root < len(nodes):
                raise ValueError(f"scenes[{s}].nodes names {root!r}: not one of the {len(nodes)} nodes")
            roots[root] += 1
    if not scenes:
        roots = [0 if parents[i] else 1 for i in range(len(nodes))]
    paths: list[int | None] = [None] * len(nodes)
    for start in range(len(nodes)):  # iterative depth-first over parents, memoised
        stack, on_stack = [start], {start}
        while stack:
            node = stack[-1]
            pending = [p for p in parents[node] if paths[p] is None]
            if pending:
                if pending[0] in on_stack:
                    raise ValueError(f"glTF nodes[{pending[0]}] is its own ancestor (a cycle in the node tree)")
                stack.append(pending[0])
                on_stack.add(pending[0])
                continue
            paths[node] = roots[node] + sum(paths[p] for p in parents[node])
            stack.pop()
            on_stack.discard(node)
    instances: dict[int, int] = {}
    for i, node in enumerate(nodes):
        if isinstance(node, dict) and "mesh" in node:
            mesh = _whole(node, "mesh", f"nodes[{i}]")
            if mesh >= meshes:
                raise ValueError(f"nodes[{i}].mesh {mesh} does not exist")
            instances[mesh] = instances.get(mesh, 0) + paths[i]
    return instances


def _decode(data: bytes) -> str:
    """UTF-8 text, or Latin-1 where it is not (every byte is a Latin-1 character)."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _latin_1_as_utf8(part: MeshPart) -> bytes:
    """`part` with its Latin-1 text re-encoded as UTF-8 (which trimesh decodes without its
    optional charset guesser); binary data after a PLY header is unchanged."""
    with part.open() as f:
        return f.read(part.latin_1).decode("latin-1").encode("utf-8") + f.read()


_COUNTERS = {"obj": _count_obj, "ply": _count_ply, "off": _count_off, "stl": _count_stl, "glb": _count_gltf,
             "gltf": _count_gltf}
