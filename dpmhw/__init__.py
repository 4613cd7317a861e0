"""dpmhw: dynamic projection mapping, from tracked pose to projected pixel."""

import os as _os

# numba's parallel kernels run on OpenMP here; its default busy-waits after every parallel
# region, and those spinning threads took the CPU from the render and Embree threads between
# kernels (a 1024×768 reconstruction frame measured 163 ms spinning vs 28 ms passive on the
# shared 2-core machine). Must be set before the OpenMP runtime loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# numba's cache for these sources (dpmhw/kernel_cache.py): before any kernel is defined
from dpmhw.kernel_cache import configure as _configure_kernel_cache  # noqa: E402

_configure_kernel_cache()

__version__ = "0.1.0"
