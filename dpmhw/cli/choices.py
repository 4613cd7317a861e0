"""Option choices as enums, so Typer checks them while parsing the command line and names the
option in its error ("Invalid value for '--reuse': 'moton' is not one of …"), before any scene
loads. Lists that the core defines are taken from the core, so a new mode appears here by itself.
"""

from __future__ import annotations

import enum

from dpmhw.display import DISPLAY_MODES
from dpmhw.postprocess import TONEMAPS
from dpmhw.reconstruct.settings import REUSE_MODES

__all__ = ["ApiMode", "BenchTrajectory", "ClientPriority", "DisplayModeChoice", "NatNetVersion", "PixelSampling", "QualityPart", "ReuseMode",
           "SerialModel", "SinkKind", "Tonemap", "Trajectory"]


def _choices(name: str, values) -> type[enum.Enum]:
    return enum.Enum(name, {v: v for v in values}, type=str)


ReuseMode = _choices("ReuseMode", REUSE_MODES)
Tonemap = _choices("Tonemap", TONEMAPS)
QualityPart = _choices("QualityPart", ("static", "dynamic", "native", "all"))
BenchTrajectory = _choices("BenchTrajectory", ("linear", "rotate-oscillate", "static"))
DisplayModeChoice = _choices("DisplayModeChoice", DISPLAY_MODES)
ApiMode = _choices("ApiMode", ("process", "thread"))
ClientPriority = _choices("ClientPriority", ("normal", "low", "idle"))
Trajectory = _choices("Trajectory", ("static", "linear", "circular", "rotate-oscillate", "recorded"))
NatNetVersion = _choices("NatNetVersion", ("3.0", "3.1", "4.0", "4.1", "4.2"))
SerialModel = _choices("SerialModel", ("LY", "PA", "LU"))
SinkKind = _choices("SinkKind", ("window", "file", "recording"))
PixelSampling = _choices("PixelSampling", ("jitter", "centre"))  # dpmhw.render.integrator.PIXEL_SAMPLING
