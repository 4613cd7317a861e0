"""Projection sessions: config, pose prediction, safety, metrics, the real-time loop, recording.

Drivers, firmware mocks and the server are imported lazily, by name, from `factory` only.
"""
