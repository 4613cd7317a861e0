"""Host side of real devices: DLPC900 projector, NatNet and serial trackers, frame sinks."""
