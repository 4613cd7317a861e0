"""A textured mesh that tests write where they need it: a checker PNG and an OBJ quad whose
texture coordinates map it once across the quad, with its MTL.

Tests import this module by name (`from textured_assets import write_checker_quad`): pytest puts
`tests/` on the import path for every test package below it."""

from pathlib import Path

import numpy as np

DARK, LIGHT = 40, 220  # the checker's two sRGB grey levels (8-bit)


def checker(cells: int = 4, texels_per_cell: int = 8) -> np.ndarray:
    """(H, W) uint8 checker, the top-left cell LIGHT."""
    index = np.arange(cells * texels_per_cell) // texels_per_cell
    return np.where((index[:, None] + index[None, :]) % 2 == 0, LIGHT, DARK).astype(np.uint8)


def write_checker_quad(folder: Path, size: float = 1.0, cells: int = 4, texels_per_cell: int = 8, mtl_extra: str = "",
                       image: str = "checker.png") -> Path:
    """checker.png, quad.mtl (map_Kd image, plus `mtl_extra` lines) and quad.obj in `folder`: a
    size × size square in the XZ plane facing +Y, u along +x, v along −z (so the image's top row
    is at −z). Returns the OBJ's path."""
    from PIL import Image

    folder = Path(folder)
    Image.fromarray(checker(cells, texels_per_cell)).convert("RGB").save(folder / "checker.png")
    (folder / "quad.mtl").write_text(f"newmtl checker\nKd 1 1 1\nmap_Kd {image}\n{mtl_extra}")
    h = size / 2
    (folder / "quad.obj").write_text(
        "mtllib quad.mtl\n"
        f"v {-h} 0 {h}\nv {h} 0 {h}\nv {h} 0 {-h}\nv {-h} 0 {-h}\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "vn 0 1 0\n"
        "usemtl checker\n"
        "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n")
    return folder / "quad.obj"
