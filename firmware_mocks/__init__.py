"""Device side of the same wires (DLPC900 over USB, NatNet, serial tracker) and a simulated world.

Never imports `drivers`: a mock that shares the driver's codec proves nothing about the wire.
"""
