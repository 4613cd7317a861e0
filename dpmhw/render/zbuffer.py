"""What the renderer's two z-buffer rasterisers share: `static_raster` (the camera's hits on the
static objects, once per camera pose, for the path tracer) and the native G-buffer's
(`gbuffer._raster_moving`, the moving objects inside their region each frame).

Both stop at one near plane. Geometry closer to the projector's plane than `NEAR_Z` is not real
content (it would sit inside the lens), and projecting a vertex that close sends its pixel
coordinates towards infinity: the static rasteriser bounds a triangle that crosses the plane by
its part beyond it, and the G-buffer hands a frame with a moving vertex there to the tracer.
Both split the image into bands of `BAND_ROWS` rows, each band's pixels written by one thread;
a pixel keeps the closest hit, the first triangle in order on a tie, so the band size changes the
threads' shares, never a hit.
"""

NEAR_Z = 1e-4  # metres in front of the projector's centre along its axis
BAND_ROWS = 16  # image rows per band
