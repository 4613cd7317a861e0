"""dpmhw: dynamic projection mapping, from tracked pose to projected pixel."""

__version__ = "0.1.0"
