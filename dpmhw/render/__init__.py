"""The renderer: cameras, Embree acceleration, the path integrator and its per-frame buffers."""
