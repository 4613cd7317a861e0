"""The reconstruction's setting values, as plain data: the session config and the operator API
take their choices and bounds from here without importing the numba kernels."""

from __future__ import annotations

REUSE_MODES = ("off", "same-pixel", "motion")
FILTER_MODES = ("off", "normal", "lobe")
MAX_HISTORY_LENGTH = 2.0**20  # history length saturates here (float32 counts exactly up to 2^24)
# α, the new frame's weight, stands for 1/α frames of history: a smaller α than the longest
# history the reuse counts cannot be honoured (and a subnormal one overflows 1/α)
ALPHA_MIN = 1.0 / MAX_HISTORY_LENGTH
ALPHA_MAX = 1.0
