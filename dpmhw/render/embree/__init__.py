"""Intel Embree, the renderer's ray queries: `capi` binds Embree 4's C API for the numba kernels,
`traversal` holds those kernels (closest hit, occlusion), and `accel` the scene's BVHs behind one
interface, built through the C API (`RtcAccel`) or through embreex's Python calls (`EmbreeAccel`,
the fallback and the tests' oracle)."""
