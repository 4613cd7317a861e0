"""Device side of the same wires (DLPC900 over USB, NatNet, serial tracker) and a simulated world.

Never imports `drivers`: a mock that shares the driver's codec proves nothing about the wire.
"""


def __getattr__(name: str):
    # `firmware_mocks.usb_emulation()` as the projector issue names it, without importing pyusb eagerly
    if name == "usb_emulation":
        from firmware_mocks.dlpc900_usb import usb_emulation

        return usb_emulation
    raise AttributeError(f"module 'firmware_mocks' has no attribute {name!r}")
