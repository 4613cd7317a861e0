"""Offline work spread over machines with Ray: converged renders and benchmark references.

`passes` defines how a render of N passes is cut into blocks and summed, in the same way whether
the blocks run here (in process, no Ray needed) or as Ray tasks (`ray_pool`, the optional
`cluster` extra): so a render split over a cluster is the local render, bit for bit. See
docs/cluster.md.
"""

from __future__ import annotations

from dpmhw.errors import DpmhwError

INSTALL_HINT = "pip install 'dpmhw[cluster]'"


class ClusterError(DpmhwError, RuntimeError):
    """Ray is missing, cannot be reached, or a worker runs a different renderer."""
