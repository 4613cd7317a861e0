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


def write_checker_quad(folder: Path, size: float = 1.0, cells: int = 4, texels_per_cell: int = 8, mtl_extra: str = "") -> Path:
    """checker.png, quad.mtl (map_Kd checker.png, plus `mtl_extra` lines) and quad.obj in `folder`: a
    size × size square in the XZ plane facing +Y, u along +x, v along −z (so the image's top row
    is at −z). Returns the OBJ's path."""
    from PIL import Image

    folder = Path(folder)
    Image.fromarray(checker(cells, texels_per_cell)).convert("RGB").save(folder / "checker.png")
    (folder / "quad.mtl").write_text(f"newmtl checker\nKd 1 1 1\nmap_Kd checker.png\n{mtl_extra}")
    h = size / 2
    (folder / "quad.obj").write_text(
        "mtllib quad.mtl\n"
        f"v {-h} 0 {h}\nv {h} 0 {h}\nv {h} 0 {-h}\nv {-h} 0 {-h}\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "vn 0 1 0\n"
        "usemtl checker\n"
        "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n")
    return folder / "quad.obj"


def write_textured_bunny(folder: Path, repeats: float = 2.0) -> Path:
    """bunny.obj (the built-in Stanford bunny with `vt` by planar projection along z: u from x,
    v from y, `repeats` checker images across it, no seam), bunny.mtl and checker.png (8 × 8
    cells) in `folder`. Returns the OBJ's path."""
    from PIL import Image

    from dpmhw.meshes import stanford_bunny

    folder = Path(folder)
    mesh = stanford_bunny(smooth=False)
    v = mesh.vertices
    lo, hi = v.min(axis=0), v.max(axis=0)
    uv = (v[:, :2] - lo[:2]) / (hi[:2] - lo[:2]).max() * repeats
    Image.fromarray(checker(cells=8, texels_per_cell=8)).convert("RGB").save(folder / "checker.png")
    (folder / "bunny.mtl").write_text("newmtl checker\nKd 1 1 1\nmap_Kd checker.png\n")
    lines = ["mtllib bunny.mtl"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in uv]
    lines.append("usemtl checker")
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in mesh.faces + 1]
    (folder / "bunny.obj").write_text("\n".join(lines) + "\n")
    return folder / "bunny.obj"


def textured_bunny_scene(folder: Path, width: int = 256, height: int = 192) -> Path:
    """The built-in dpm-bunny scene at width × height with the textured bunny (write_textured_bunny),
    seen by its projector (no separate viewer)."""
    from importlib.resources import files

    write_textured_bunny(folder)
    text = files("dpmhw.scenes").joinpath("dpm-bunny.toml").read_text()
    scale = width / 1024
    text = (text.replace('mesh = "builtin:bunny"', 'mesh = "bunny.obj"')
            .replace("width = 1024", f"width = {width}").replace("height = 768", f"height = {height}")
            .replace("fx = 1500.0", f"fx = {1500 * scale}").replace("fy = 1500.0", f"fy = {1500 * scale}")
            .replace("cx = 512.0", f"cx = {512 * scale}").replace("cy = 700.0", f"cy = {700 * scale}")
            .replace("albedo = [0.65, 0.55, 0.45]", "albedo = [0.9, 0.8, 0.7]")
            .replace("[viewer]\nposition = [0.5, 0.3, 1.2]\n", ""))  # Mitsuba shades towards the camera
    path = folder / "textured-bunny.toml"
    path.write_text(text)
    return path
