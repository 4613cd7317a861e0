"""A small scene: the tests' lit room with a turning mesh read from an OBJ file by a relative path."""

import textwrap

import pytest
from scene_texts import lit_room

from dpmhw.scene_file import load_scene

SCENE = lit_room("""
[[objects]]
name = "wedge"
shape = "mesh"
mesh = "meshes/wedge.obj"
scale = 0.4
position = [0.0, 0.0, 0.0]
rotation = [0.0, 30.0, 0.0]
albedo = [0.5, 0.6, 0.5]
specular = [0.3, 0.3, 0.3]
roughness = 0.3
motion = { rotate_axis = [0.0, 1.0, 0.0], rotate_deg_per_s = 60.0 }
""", width=40, height=30, f=32.0, cx=20.0, cy=15.0, max_bounces=1)

WEDGE_OBJ = """\
v -0.5 0 -0.5
v 0.5 0 -0.5
v 0.5 0 0.5
v -0.5 0 0.5
v -0.5 0.8 0
v 0.5 0.8 0
f 1 2 3
f 1 3 4
f 4 3 6
f 4 6 5
f 1 5 6
f 1 6 2
f 1 4 5
f 2 6 3
"""


@pytest.fixture
def scene_file(tmp_path):
    """scene.toml in its own folder, its mesh at meshes/wedge.obj beside it."""
    folder = tmp_path / "lab-scene"
    (folder / "meshes").mkdir(parents=True)
    (folder / "meshes" / "wedge.obj").write_text(WEDGE_OBJ)
    path = folder / "scene.toml"
    path.write_text(textwrap.dedent(SCENE))
    return path


@pytest.fixture
def scene(scene_file):
    return load_scene(scene_file)
