"""Shared synthetic worlds: rendered and decoded once per test session (small resolutions)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from calibration.procam import Observation, ProcamResult, calibrate_procam, observe
from calibration.synthetic import SyntheticRig, make_rig

PROJECTOR = (400, 300)
CAMERA = (640, 480)


@dataclass
class World:
    rig: SyntheticRig
    observations: list[Observation]
    result: ProcamResult


def observe_all(rig: SyntheticRig) -> list[Observation]:
    return [observe(f"pose_{i:03d}", rig.render_view(i), rig.board, (rig.projector.width, rig.projector.height)) for i in range(len(rig.views))]


@pytest.fixture(scope="session")
def world() -> World:
    """13 tilted poses, projector cy 3 % below the image (lens shift), noise 1.5 DN, blur 0.7 px."""
    rig = make_rig(seed=1, n_views=13, camera_size=CAMERA, projector_size=PROJECTOR, supersample=1)
    obs = observe_all(rig)
    return World(rig, obs, calibrate_procam(obs, rig.board, PROJECTOR))
