import textwrap

import pytest

from dpmhw.render.integrator import PathIntegrator
from dpmhw.scene_file import load_scene


@pytest.fixture
def make_scene(tmp_path):
    """Write a TOML scene (dedented) to a file and load it."""

    def make(text: str, name: str = "scene.toml"):
        path = tmp_path / name
        path.write_text(textwrap.dedent(text))
        return load_scene(path)

    return make


@pytest.fixture
def render():
    """Render a scene and close the integrator afterwards."""

    def run(scene, spp=1, seed=0, time=0.0, **kwargs):
        with PathIntegrator(scene, **kwargs) as integrator:
            return integrator.render(time=time, seed=seed, spp=spp)

    return run


@pytest.fixture
def np_rng():
    import numpy as np

    return np.random.default_rng(12345)
