"""Albedo textures of mesh files: the base-colour image a mesh declares (an OBJ material's
`map_Kd`, a PLY's `comment TextureFile`, a glTF's `baseColorTexture`), decoded to linear RGB
within the memory budget, and what else an OBJ's materials declare that the renderer does not
model (named in one warning).

The renderer multiplies an object's albedo by its texture, fetched bilinearly with repeat
wrapping (`kernels.albedo_at`). Texels are stored in sRGB and decoded to linear once here, as a
renderer reading an 8-bit colour image does (Mitsuba's `bitmap` without `raw`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from dpmhw.postprocess import srgb_decode

__all__ = ["BYTES_PER_TEXEL", "MTL_MODELLED", "Texture", "decode_texture", "open_texture", "parse_mtl"]

# Peak bytes per texel of loading a texture: the peak RSS of `load_mesh` on a quad with an
# incompressible (noise) PNG of 1024², 2048² and 4096² texels over its RSS before, per texel:
# 25.0, 22.3 and 22.1 (the file's bytes, Pillow's 4-byte pixels, the 8-bit array, the float32
# linear texels); taken as 24. The renderer then reads the mesh's texels in place.
BYTES_PER_TEXEL = 24

# MTL statements the renderer reads or that change nothing it draws: the material's name, its
# base-colour image, and the illumination model and optical constants exporters always write (the
# scene's albedo, specular and roughness are the material; `Kd` is reported when it is not 1,
# `Ks` and `Ke` when not 0).
MTL_MODELLED = {"newmtl", "map_kd", "illum", "ka", "ks", "ns", "ni", "d", "tr", "tf", "kd"}


@dataclass
class Texture:
    """texels : (H, W, 3) float32 linear RGB, row 0 the image's top (v = 1); source : the file."""

    texels: np.ndarray
    source: str

    @property
    def size(self) -> tuple[int, int]:
        return self.texels.shape[1], self.texels.shape[0]


_LINEAR_OF_BYTE = srgb_decode(np.arange(256) / 255.0).astype(np.float32)


def open_texture(data: bytes):
    """The image in `data` with its header read and its pixels not yet decoded (Pillow decodes
    lazily), so that its size can be charged before the decode. Raises what Pillow raises."""
    from PIL import Image

    return Image.open(io.BytesIO(data))


def decode_texture(image, name: str) -> tuple[Texture, list[str]]:
    """(the linear texture, notes): decodes a lazily opened image (`open_texture`; raises what
    Pillow raises for broken data); a note names an alpha channel that is not opaque
    (transparency is not modelled)."""
    notes = []
    if image.mode.startswith("I;16"):  # 16-bit grey: its high bytes
        image = image.point(lambda value: value / 256).convert("L")
    if image.mode not in ("RGB", "RGBA", "L", "LA"):
        image = image.convert("RGBA" if "A" in image.getbands() or image.mode == "P" else "RGB")
    pixels = np.asarray(image)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if pixels.shape[2] in (2, 4):
        if pixels[:, :, -1].min() < 255:
            notes.append(f"texture {name} has transparent texels: alpha is not modelled (drawn opaque)")
        pixels = pixels[:, :, :-1]
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    return Texture(_LINEAR_OF_BYTE[pixels], name), notes


def parse_mtl(text: str, used: set[str] | None) -> tuple[dict[str, str], list[str]]:
    """({material: map_Kd file name}, [statements the renderer does not model]) of the MTL
    `text`, for the materials in `used` (None: all). Each unmodelled statement is named once."""
    maps: dict[str, str] = {}
    ignored: dict[str, None] = {}
    material = None
    for line in text.splitlines():
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        key = words[0].lower()
        if key == "newmtl":
            material = " ".join(words[1:])
            continue
        if used is not None and material not in used:
            continue
        if key == "map_kd" and len(words) > 1:
            maps[material] = _map_file(words[1:])
        elif key == "kd" and len(words) > 1 and any(_number(w) != 1.0 for w in words[1:4]):
            ignored[f"Kd {' '.join(words[1:4])} (the scene's albedo is used)"] = None
        elif key == "ks" and any(_number(w) != 0.0 for w in words[1:4]):
            ignored[f"Ks {' '.join(words[1:4])} (the scene's specular is used)"] = None
        elif key == "ke" and any(_number(w) != 0.0 for w in words[1:4]):
            ignored["Ke (emission: the scene's emission is used)"] = None
        elif key not in MTL_MODELLED:
            is_map = key.startswith("map_") or key in ("bump", "norm", "disp", "decal", "refl")
            ignored[words[0] + (f" {_map_file(words[1:])}" if is_map else "")] = None
    return maps, list(ignored)


def _map_file(words: list[str]) -> str:
    """The file name of a map statement's arguments: the words after its options (-o u v w, -bm s, ...)."""
    at = 0
    while at < len(words) - 1 and words[at].startswith("-"):
        option = words[at].lower()
        at += 1
        count = 3 if option in ("-o", "-s", "-t") else 2 if option == "-mm" else 1
        for _ in range(count):
            if at < len(words) - 1 and (count == 1 or _number(words[at]) is not None):
                at += 1
    return " ".join(words[at:])


def _number(word: str) -> float | None:
    try:
        return float(word)
    except ValueError:
        return None
