"""Image-space reconstruction between the renderer and the projector.

A frame is shaded at ``shading_scale`` of the projector's native size and reconstructed at
native size: temporal reuse (`reuse`, at the shading resolution), specular-lobe-aware
cross-bilateral filtering (`weights`, `filter`), joint bilateral upsampling against the native
G-buffer (`upsample`), driven by the loop through `stage.ReconstructStage`.
"""
