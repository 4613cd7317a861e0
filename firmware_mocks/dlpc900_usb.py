"""An emulated DLPC900 on the USB bus, as a pyusb backend (`usb.backend.IBackend`).

The backend enumerates one or more 0451:C900 devices with a USB 1.1 HID descriptor set
(one interface, interrupt IN 0x81 and OUT 0x01, 64-byte reports) and answers the DLPC900
framing from `protocols.md`: it reassembles multi-report messages, hands complete commands to
`DLPC900Model`, and queues reply reports (a new command overwrites an unread reply, as on the
real controller). Inside `usb_emulation()` even `usb.core.find(idVendor=0x0451,
idProduct=0xc900)` without a backend argument finds it, so unmodified host programs run against
it. Faults (unplug, stall, lost replies, error and malformed replies) are injected per device.

Never imports `drivers`.
"""

from __future__ import annotations

import contextlib
import errno
import struct
import time
from array import array
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterator

import usb.backend
import usb.core

from firmware_mocks.dlpc900_model import ERROR_NAMES, CommandError, DLPC900Model, LoggedCommand, RecentLog

VID, PID = 0x0451, 0xC900
EP_OUT, EP_IN = 0x01, 0x81
REPORT = 64
CMD_BUFFER = 512  # the controller's command buffer: header + command + data

# libusb's error numbers and texts, so host code sees what it would see on hardware.
_ERR = {
    errno.ENODEV: (-4, "No such device (it may have been disconnected)"),
    errno.EPIPE: (-9, "Pipe error"),
    errno.ENOENT: (-5, "Entity not found"),
    errno.EBUSY: (-6, "Resource busy"),
    errno.EINVAL: (-2, "Invalid parameter"),
}


def _usb_error(code: int) -> usb.core.USBError:
    backend_code, text = _ERR[code]
    return usb.core.USBError(text, backend_code, code)


def _timeout() -> usb.core.USBTimeoutError:
    return usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)


class _Desc:
    def __init__(self, **fields):
        self.__dict__.update(fields)


HID_REPORT_DESCRIPTOR = bytes([
    0x06, 0x00, 0xFF, 0x09, 0x01, 0xA1, 0x01,              # vendor page, application collection
    0x19, 0x01, 0x29, 0x40, 0x15, 0x00, 0x26, 0xFF, 0x00,  # 64 usages, 0..255
    0x75, 0x08, 0x95, 0x40, 0x81, 0x02,                    # 64 x 8-bit input
    0x19, 0x01, 0x29, 0x40, 0x91, 0x02,                    # 64 x 8-bit output
    0xC0,
])
HID_DESCRIPTOR = bytes([9, 0x21, 0x11, 0x01, 0, 1, 0x22]) + struct.pack("<H", len(HID_REPORT_DESCRIPTOR))


@dataclass
class _Handle:
    device: "EmulatedDLPC900"
    generation: int
    configuration: int = 1


class EmulatedDLPC900:
    """One emulated controller: its model, its USB identity and the faults queued for it."""

    def __init__(self, serial: str, *, bus: int = 1, address: int = 5, model: DLPC900Model | None = None,
                 clock: Callable[[], int] = time.monotonic_ns):
        self.serial = serial
        self.bus, self.address = bus, address
        self.model = model or DLPC900Model(clock=clock)
        self.plugged = True
        self.generation = 0
        self._partial: bytearray | None = None
        self._need = 0
        self._overlong: tuple[int, int, int] | None = None  # (flags, seq, opcode) of a message being discarded
        self._in: deque[bytes] = deque()
        self.raw_out: RecentLog = RecentLog()  # the OUT reports as received (the newest ones)
        self.raw_in: RecentLog = RecentLog()  # the IN reports as sent (the newest ones)
        self._faults: list[dict] = []
        self._stall = 0
        self.claimed = False

    # ---- fault injection -------------------------------------------------------------
    def unplug(self) -> None:
        """The cable comes out: every transfer and open fails with ENODEV until `replug`."""
        self.plugged = False

    def replug(self, *, power_cycle: bool = True) -> None:
        """Plug back in with a new address; `power_cycle` resets the controller to power-on state."""
        self.plugged = True
        self.generation += 1
        self.address += 1
        self._partial, self._overlong, self._in = None, None, deque()
        self.claimed = False
        if power_cycle:
            self.model.power_on()

    def stall(self, transfers: int = 1) -> None:
        """The next `transfers` interrupt transfers fail with EPIPE (a halted endpoint)."""
        self._stall += transfers

    def drop_replies(self, count: int = 1, opcode: int | None = None) -> None:
        """Answer nothing to the next `count` commands (matching `opcode`): host reads time out."""
        self._faults.append(dict(kind="drop", opcode=opcode, left=count))

    def fail_commands(self, code: int, count: int = 1, opcode: int | None = None, description: str | None = None) -> None:
        """Reject the next `count` commands (matching `opcode`) with error `code`."""
        self._faults.append(dict(kind="error", opcode=opcode, left=count, code=code,
                                 description=description or ERROR_NAMES.get(code, "error")))

    def corrupt_replies(self, how: str, count: int = 1, opcode: int | None = None) -> None:
        """Malform the next replies: 'short' (2 bytes), 'sequence' (wrong sequence byte),
        'length' (length field off by +3), 'flags' (error bit set on a success)."""
        if how not in ("short", "sequence", "length", "flags"):
            raise ValueError(f"corrupt_replies: unknown kind {how!r}")
        self._faults.append(dict(kind=how, opcode=opcode, left=count))

    def _take_fault(self, opcode: int, kinds: tuple[str, ...]) -> dict | None:
        for f in self._faults:
            if f["kind"] in kinds and f["left"] > 0 and f["opcode"] in (None, opcode):
                f["left"] -= 1
                if f["left"] == 0:
                    self._faults.remove(f)
                return f
        return None

    # ---- the HID link ----------------------------------------------------------------
    def _check_link(self) -> None:
        if not self.plugged:
            raise _usb_error(errno.ENODEV)
        if self._stall:
            self._stall -= 1
            raise _usb_error(errno.EPIPE)

    def receive(self, report: bytes) -> None:
        """One OUT report from the host: start or continue a message, run it when complete.

        The length field frames a message: the reports after its first one are its continuation,
        never commands of their own. A message longer than the 512-byte command buffer is not
        stored, but its continuation is still counted off and discarded; once it has all arrived
        the controller answers once, with error 8.
        """
        self.raw_out.append(bytes(report))
        if self._partial is None:
            if len(report) < 6:
                self._latch(3, "report too short for a command header")
                return
            length = report[2] | (report[3] << 8)
            total = 4 + length
            if length < 2:
                self._reply_error(report[0], report[1], 0, 3, f"length field {length} < 2")
                return
            self._partial, self._need = bytearray(), total
            if total > CMD_BUFFER:
                self._overlong = (report[0], report[1], report[4] | (report[5] << 8))
        if self._overlong is None:
            self._partial += report[: self._need - len(self._partial)]
            got = len(self._partial)
        else:  # count the bytes, keep none of them
            self._need -= min(len(report), self._need)
            got = 0
        if got >= self._need:
            msg, self._partial = bytes(self._partial), None
            if self._overlong is None:
                self._run(msg)
                return
            (flags, seq, opcode), self._overlong = self._overlong, None
            self._reply_error(flags, seq, opcode, 8, "message exceeds the 512-byte command buffer")

    def _latch(self, code: int, description: str) -> None:
        self.model.error_code = code
        self.model.error_description = description

    def _reply_error(self, flags: int, seq: int, opcode: int, code: int, description: str) -> None:
        self._latch(code, description)
        self.model.command_log.append(LoggedCommand(self.model.clock(), seq, opcode, bool(flags & 0x80),
                                                    bool(flags & 0x40), b"", code))
        if flags & 0xC0:
            self._queue_reply(flags | 0x20, seq, b"", opcode)

    def _run(self, msg: bytes) -> None:
        flags, seq = msg[0], msg[1]
        opcode = msg[4] | (msg[5] << 8)
        data = msg[6:]
        read = bool(flags & 0x80)
        code, reply = 0, b""
        forced = self._take_fault(opcode, ("error",))
        if forced is not None:
            code, description = forced["code"], forced["description"]
        else:
            try:
                reply = self.model.execute(opcode, data, read)
            except CommandError as exc:
                code, description = exc.code, exc.description
            except Exception as exc:  # a model bug must not kill the emulated device
                code, description = 255, f"internal error: {exc!r}"
        self.model.command_log.append(LoggedCommand(self.model.clock(), seq, opcode, read, bool(flags & 0x40), data, code))
        if code:
            self._latch(code, description)
        elif not (read and opcode in (0x0100, 0x0101)):  # reading the error keeps it
            self._latch(0, "")
        if read or flags & 0x40:
            self._queue_reply(flags | (0x20 if code else 0), seq, b"" if code else reply, opcode)

    def _queue_reply(self, flags: int, seq: int, data: bytes, opcode: int) -> None:
        self._in.clear()  # an unread reply is overwritten by the next one
        if self._take_fault(opcode, ("drop",)):
            return
        length = len(data)
        bad = self._take_fault(opcode, ("short", "sequence", "length", "flags"))
        kind = bad["kind"] if bad else None
        if kind == "short":
            self._in.append(bytes([flags, seq]))
            return
        if kind == "sequence":
            seq = (seq + 1) & 0xFF
        if kind == "length":
            length += 3
        if kind == "flags":
            flags |= 0x20
        msg = bytes([flags, seq]) + struct.pack("<H", length) + data
        for i in range(0, len(msg), REPORT):
            self._in.append(msg[i:i + REPORT].ljust(REPORT, b"\x00"))

    def send(self, size: int) -> bytes:
        """Next IN report, or a timeout if the controller has nothing to say."""
        if not self._in:
            raise _timeout()
        report = self._in.popleft()[:size]
        self.raw_in.append(report)
        return report

    # ---- descriptors -------------------------------------------------------------------
    def device_descriptor(self) -> _Desc:
        return _Desc(bLength=18, bDescriptorType=1, bcdUSB=0x0110, bDeviceClass=0, bDeviceSubClass=0,
                     bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=VID, idProduct=PID, bcdDevice=0x0100,
                     iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
                     address=self.address, bus=self.bus, port_number=1, port_numbers=(1,), speed=2)

    def strings(self) -> dict[int, str]:
        return {1: "Texas Instruments", 2: "DLPC900", 3: self.serial}


_CONFIG = _Desc(bLength=9, bDescriptorType=2, wTotalLength=9 + 9 + 9 + 7 + 7, bNumInterfaces=1,
                bConfigurationValue=1, iConfiguration=0, bmAttributes=0xC0, bMaxPower=50, extra_descriptors=[])
_INTERFACE = _Desc(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=2,
                   bInterfaceClass=3, bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0,
                   extra_descriptors=list(HID_DESCRIPTOR))
_ENDPOINTS = [
    _Desc(bLength=7, bDescriptorType=5, bEndpointAddress=EP_IN, bmAttributes=3, wMaxPacketSize=REPORT,
          bInterval=1, bRefresh=0, bSynchAddress=0, extra_descriptors=[]),
    _Desc(bLength=7, bDescriptorType=5, bEndpointAddress=EP_OUT, bmAttributes=3, wMaxPacketSize=REPORT,
          bInterval=1, bRefresh=0, bSynchAddress=0, extra_descriptors=[]),
]


def _pack_device(d: _Desc) -> bytes:
    return struct.pack("<BBHBBBBHHHBBBB", 18, 1, d.bcdUSB, 0, 0, 0, 64, VID, PID, d.bcdDevice, 1, 2, 3, 1)


def _pack_config() -> bytes:
    c = _CONFIG
    out = struct.pack("<BBHBBBBB", 9, 2, c.wTotalLength, 1, 1, 0, c.bmAttributes, c.bMaxPower)
    out += struct.pack("<BBBBBBBBB", 9, 4, 0, 0, 2, 3, 0, 0, 0) + HID_DESCRIPTOR
    for e in _ENDPOINTS:
        out += struct.pack("<BBBBHB", 7, 5, e.bEndpointAddress, 3, REPORT, 1)
    return out


class DLPC900Backend(usb.backend.IBackend):
    """pyusb backend whose bus holds only emulated DLPC900s."""

    def __init__(self, devices: list[EmulatedDLPC900]):
        super().__init__()
        self.devices = devices

    # enumeration and descriptors
    def enumerate_devices(self):
        for d in self.devices:
            if d.plugged:
                yield d

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return dev.device_descriptor()

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError("configuration index out of range")
        return _CONFIG

    def get_interface_descriptor(self, dev, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError("interface / alternate setting out of range")
        return _INTERFACE

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0 or ep not in (0, 1):
            raise IndexError("endpoint index out of range")
        return _ENDPOINTS[ep]

    # handles
    def _live(self, handle: _Handle) -> EmulatedDLPC900:
        dev = handle.device
        if not dev.plugged or handle.generation != dev.generation:
            raise _usb_error(errno.ENODEV)
        return dev

    def open_device(self, dev):
        if not dev.plugged:
            raise _usb_error(errno.ENODEV)
        return _Handle(dev, dev.generation)

    def close_device(self, dev_handle):
        if dev_handle.generation == dev_handle.device.generation:
            dev_handle.device.claimed = False

    def set_configuration(self, dev_handle, config_value):
        self._live(dev_handle)
        if config_value not in (0, 1):
            raise _usb_error(errno.EINVAL)
        dev_handle.configuration = config_value

    def get_configuration(self, dev_handle):
        self._live(dev_handle)
        return dev_handle.configuration

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._live(dev_handle)
        if intf != 0 or altsetting != 0:
            raise _usb_error(errno.EINVAL)

    def claim_interface(self, dev_handle, intf):
        dev = self._live(dev_handle)
        if intf != 0:
            raise _usb_error(errno.ENOENT)
        dev.claimed = True

    def release_interface(self, dev_handle, intf):
        dev = self._live(dev_handle)
        dev.claimed = False

    def is_kernel_driver_active(self, dev_handle, intf):
        self._live(dev_handle)
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        self._live(dev_handle)

    def attach_kernel_driver(self, dev_handle, intf):
        self._live(dev_handle)

    def clear_halt(self, dev_handle, ep):
        self._live(dev_handle)._stall = 0

    def reset_device(self, dev_handle):
        dev = self._live(dev_handle)
        dev._partial, dev._overlong, dev._in = None, None, deque()

    # transfers
    def intr_write(self, dev_handle, ep, intf, data, timeout):
        dev = self._live(dev_handle)
        if ep != EP_OUT:
            raise _usb_error(errno.EINVAL)
        dev._check_link()
        payload = bytes(data)
        for i in range(0, max(len(payload), 1), REPORT):
            dev.receive(payload[i:i + REPORT])
        return len(payload)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        dev = self._live(dev_handle)
        if ep != EP_IN:
            raise _usb_error(errno.EINVAL)
        dev._check_link()
        report = dev.send(len(buff))
        buff[: len(report)] = array("B", report)
        return len(report)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        dev = self._live(dev_handle)
        if bmRequestType in (0x80, 0x81) and bRequest == 0x06:  # GET_DESCRIPTOR
            kind, index = wValue >> 8, wValue & 0xFF
            if kind == 1:
                blob = _pack_device(dev.device_descriptor())
            elif kind == 2:
                blob = _pack_config()
            elif kind == 3:
                if index == 0:
                    blob = bytes([4, 3, 0x09, 0x04])
                elif index in dev.strings():
                    text = dev.strings()[index].encode("utf-16-le")
                    blob = bytes([2 + len(text), 3]) + text
                else:
                    raise _usb_error(errno.EPIPE)
            elif kind == 0x22:
                blob = HID_REPORT_DESCRIPTOR
            else:
                raise _usb_error(errno.EPIPE)
            n = min(len(blob), len(data))
            data[:n] = array("B", blob[:n])
            return n
        if bmRequestType == 0x80 and bRequest == 0x00:  # GET_STATUS: self powered
            data[:2] = array("B", b"\x01\x00")
            return 2
        if bmRequestType == 0x21 and bRequest == 0x0A:  # HID SET_IDLE
            return 0
        if bmRequestType == 0x21 and bRequest == 0x09:  # HID SET_REPORT: an OUT report over EP0
            dev._check_link()
            dev.receive(bytes(data))
            return len(data)
        if bmRequestType == 0xA1 and bRequest == 0x01:  # HID GET_REPORT
            report = dev.send(len(data))
            data[: len(report)] = array("B", report)
            return len(report)
        raise _usb_error(errno.EPIPE)  # unsupported request: the device stalls EP0


@contextlib.contextmanager
def usb_emulation(*serials: str, clock: Callable[[], int] = time.monotonic_ns,
                  width: int | None = None, height: int | None = None, dmd_type: int = 1) -> Iterator[EmulatedDLPC900]:
    """Put emulated DLPC900s on pyusb's default bus for the duration of the block.

    Yields the first device (its `.model`, fault methods, `.backend`); the backend's `.devices`
    lists all of them. On exit pyusb's own backends are restored. `dmd_type` as 0x0206 reports
    it (1 DLP6500, 2 DLP9000 with two controllers); `width` and `height` default to its native
    resolution.
    """
    import usb.backend.libusb0 as libusb0
    import usb.backend.libusb1 as libusb1
    import usb.backend.openusb as openusb

    serials = serials or ("EMU0001",)
    devices = [EmulatedDLPC900(s, address=5 + 3 * i, model=DLPC900Model(clock=clock, width=width, height=height,
                                                                      dmd_type=dmd_type))
               for i, s in enumerate(serials)]
    backend = DLPC900Backend(devices)
    for d in devices:
        d.backend = backend
    saved = [(m, m.get_backend) for m in (libusb1, openusb, libusb0)]
    for m, _ in saved:
        m.get_backend = lambda *args, **kwargs: backend
    try:
        yield devices[0]
    finally:
        for m, fn in saved:
            m.get_backend = fn
