"""The emulated DLPC900 in its own process, reached through a pyusb backend over a local socket.

A real projector lives outside the host process: it keeps its state when the program driving it
dies, and the kernel releases the dead program's claim on it. `usb_emulation()` cannot show
that (the device dies with the process), so a supervisor that idles the projector after a crash
could not be tested on it. Here `EmulatorProcess` runs the same `EmulatedDLPC900`s (wrapped,
unchanged) behind a Unix socket, and `socket_usb(address, authkey)` puts a `SocketBackend` on
pyusb's default bus in any process, so unmodified host code (the driver) finds the device:

    emulator = EmulatorProcess.start()                    # a child process; .address, .authkey
    with socket_usb(emulator.address, emulator.authkey):  # in this or any other process
        ...                                               # usb.core.find(idVendor=0x0451, …)
    emulator.inspect()                                    # what the device shows (for tests)
    emulator.close()

Each backend call is one request/reply on a `multiprocessing.connection` (authenticated with
the key, so no other local user can drive the projector). A client whose connection drops
(its process died) loses its interface claims, as with the kernel's usbfs. If the emulator
itself is gone, every transfer fails with ENODEV, as for an unplugged cable.

No client can hold up another: each connection is served on its own thread (at most
`MAX_CLIENTS`), its handshake must finish within `HANDSHAKE_TIMEOUT_S`, a request is at most
`MAX_REQUEST_BYTES` and a transfer at most `MAX_TRANSFER` bytes (wLength is 16 bits), and a
malformed request gets an error reply. On the host side every exchange is bounded by
`REPLY_TIMEOUT_S` (a stuck emulator reads as a USB timeout, as a stuck device would).
The socket's folder is named by the owner's pid (`EMULATOR_DIRS`): the emulator removes it when
its owner dies, the owner when it closes the emulator, and `EmulatorProcess.start` any left by a
dead owner (both killed).

Never imports `drivers`.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import multiprocessing
import os
import pickle
import secrets
import shutil
import signal
import socket
import struct
import tempfile
import threading
import time
from multiprocessing.connection import Connection, Listener, answer_challenge, deliver_challenge
from typing import Any, Iterator

import usb.backend
import usb.core

from dpmhw.child_process import OwnedNames
from firmware_mocks.dlpc900_model import DLPC900Model
from firmware_mocks.dlpc900_usb import DLPC900Backend, EmulatedDLPC900, _Desc, _Handle, _timeout, _usb_error

__all__ = ["EMULATOR_DIRS", "EmulatorProcess", "SocketBackend", "serve", "socket_usb"]

log = logging.getLogger(__name__)

_DESCRIPTORS = ("get_device_descriptor", "get_configuration_descriptor", "get_interface_descriptor",
                "get_endpoint_descriptor")
_ON_HANDLE = ("close_device", "set_configuration", "get_configuration", "set_interface_altsetting",
              "claim_interface", "release_interface", "is_kernel_driver_active", "detach_kernel_driver",
              "attach_kernel_driver", "clear_halt", "reset_device", "intr_write")

HANDSHAKE_TIMEOUT_S = 2.0  # a connection that has not authenticated by then is dropped
REPLY_TIMEOUT_S = 5.0  # host side: an emulator that has not answered by then is a USB timeout
MAX_CLIENTS = 64  # connections served at once (each has a thread); more are closed at once
MAX_REQUEST_BYTES = 1 << 20  # one pickled request: a 16-bit transfer and its framing fit many times
MAX_TRANSFER = 0xFFFF  # a control transfer's wLength is 16 bits; no interrupt report is longer
EMULATOR_DIRS = OwnedNames(tempfile.gettempdir(), "dpmhw-dlpc900")
SOCKET_PATH_MAX = 107  # bytes of an AF_UNIX address on Linux (sun_path is 108, with its NUL)


# ---- the emulator process -------------------------------------------------------------------
class _Session:
    """One client connection: its open handles (released when it goes away)."""

    def __init__(self, backend: DLPC900Backend, lock: threading.Lock):
        self.backend, self.lock = backend, lock
        self.handles: dict[int, _Handle] = {}
        self.next_id = 1

    def call(self, op: str, args: tuple) -> Any:
        b = self.backend
        if op == "enumerate":
            return [b.devices.index(d) for d in b.enumerate_devices()]
        if op == "inspect":
            return [_inspect(d) for d in b.devices]
        if op in _DESCRIPTORS:
            return vars(getattr(b, op)(b.devices[args[0]], *args[1:]))
        if op == "open_device":
            handle = b.open_device(b.devices[args[0]])
            self.handles[self.next_id] = handle
            self.next_id += 1
            return self.next_id - 1
        handle = self.handles[args[0]]
        if op == "close_device":
            self.handles.pop(args[0])
        if op in _ON_HANDLE:
            return getattr(b, op)(handle, *args[1:])
        if op == "intr_read":  # (handle, ep, intf, size, timeout) -> bytes
            buff = bytearray(_transfer_size("intr_read", "size", args[3]))
            n = b.intr_read(handle, args[1], args[2], memoryview(buff), args[4])
            return bytes(buff[:n])
        if op == "ctrl_transfer":  # (handle, type, request, value, index, data or size, timeout)
            data = args[5]
            if isinstance(data, int):  # device-to-host: a buffer of that size
                buff = bytearray(_transfer_size("ctrl_transfer", "wLength", data))
                n = b.ctrl_transfer(handle, *args[1:5], memoryview(buff), args[6])
                return bytes(buff[:n])
            _transfer_size("ctrl_transfer", "wLength", len(data))
            return b.ctrl_transfer(handle, *args[1:5], bytes(data), args[6])
        raise ValueError(f"unknown backend operation {op!r}")

    def release(self) -> None:
        """The client is gone: drop its claims, as the kernel does for a dead process."""
        with self.lock:
            for handle in self.handles.values():
                self.backend.close_device(handle)
            self.handles.clear()


def _transfer_size(op: str, field: str, size: Any) -> int:
    if type(size) is not int or not 0 <= size <= MAX_TRANSFER:
        raise ValueError(f"{op}: {field} must be an integer 0..{MAX_TRANSFER}, not {size!r:.40}")
    return size


def _inspect(d: EmulatedDLPC900) -> dict:
    m = d.model
    return {"serial": d.serial, "plugged": d.plugged, "claimed": d.claimed, "dark": bool(m.dark),
            "idle": bool(m.idle), "standby": bool(m.standby), "parked": bool(m.parked)}


def _set_timeout(conn: Connection, seconds: float) -> None:
    """Bound every read and write on `conn` (0: none). SO_RCVTIMEO works on the descriptor, so
    it also bounds `Connection`'s own reads (an expired one raises BlockingIOError)."""
    sec = int(seconds)
    value = struct.pack("ll", sec, int((seconds - sec) * 1e6))
    with socket.socket(fileno=os.dup(conn.fileno())) as sock:  # options belong to the socket, not the fd
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, value)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, value)


def _request(conn: Connection) -> tuple[str, tuple]:
    """The next request; raises ValueError for one that is too long or not (operation, arguments)."""
    data = conn.recv_bytes(MAX_REQUEST_BYTES)  # OSError for a longer one: its bytes stay unread
    try:
        request = pickle.loads(data)
    except Exception as exc:
        raise ValueError(f"request: not a pickled (operation, arguments) pair ({type(exc).__name__})") from None
    if not (type(request) is tuple and len(request) == 2 and type(request[0]) is str and type(request[1]) is tuple):
        raise ValueError(f"request: must be (operation: str, arguments: tuple), not {type(request).__name__}")
    return request


def _serve_client(conn: Connection, session: _Session) -> None:
    try:
        while True:
            try:
                op, args = _request(conn)
            except ValueError as exc:  # malformed: say so, and wait for the next one
                reply = ("error", ("ValueError", str(exc)))
            except OSError as exc:
                if "bad message length" in str(exc):  # multiprocessing's words for over MAX_REQUEST_BYTES
                    with contextlib.suppress(OSError):
                        conn.send(("error", ("ValueError", f"request: longer than {MAX_REQUEST_BYTES} bytes")))
                return
            except EOFError:
                return
            else:
                try:
                    with session.lock:  # one controller: commands from all clients in one order
                        reply = ("ok", session.call(op, args))
                except usb.core.USBError as exc:
                    reply = ("usb", (type(exc) is usb.core.USBTimeoutError, exc.strerror, exc.backend_error_code,
                                     exc.errno))
                except Exception as exc:  # IndexError from descriptor lookups, bad arguments
                    reply = ("error", (type(exc).__name__, str(exc)))
            try:
                conn.send(reply)
            except OSError:
                return
    finally:
        session.release()
        conn.close()


def _accept(conn: Connection, authkey: bytes, session: _Session, slots: threading.BoundedSemaphore) -> None:
    """One connection's thread: the handshake within HANDSHAKE_TIMEOUT_S, then its requests."""
    try:
        try:
            _set_timeout(conn, HANDSHAKE_TIMEOUT_S)
            deliver_challenge(conn, authkey)
            answer_challenge(conn, authkey)
            _set_timeout(conn, 0)  # an authenticated client may stay quiet as long as it likes
        except multiprocessing.AuthenticationError as exc:
            log.warning("DLPC900 emulator: refused a connection: %s", exc)
            conn.close()
            return
        except (OSError, EOFError) as exc:  # left, or silent past the timeout
            log.info("DLPC900 emulator: dropped a connection during its handshake: %s", exc or type(exc).__name__)
            conn.close()
            return
        _serve_client(conn, session)
    finally:
        slots.release()


def serve(address: str, authkey: bytes, serials: tuple[str, ...] = ("EMU0001",), width: int = 1920,
          height: int = 1080, ready=None, video_hz: float | None = None) -> None:
    """Run emulated controllers behind `address` until the process is killed (or `ready` closes).
    With `video_hz` each one's video input is locked to a source at that refresh rate (a
    machine's display output scans out whether or not a program presents to it)."""
    # a terminal's Ctrl-C reaches the whole process group: the device stays on, as a real one does
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    devices = [EmulatedDLPC900(s, address=5 + 3 * i, model=DLPC900Model(width=width, height=height))
               for i, s in enumerate(serials)]
    for d in devices:
        d.model.video_period_ns = None if video_hz is None else round(1e9 / video_hz)
    backend = DLPC900Backend(devices)
    lock = threading.Lock()
    slots = threading.BoundedSemaphore(MAX_CLIENTS)
    with Listener(address, family="AF_UNIX", backlog=MAX_CLIENTS) as listener:  # authenticated per connection, on its thread
        if ready is not None:
            ready.send("ready")
            # the parent's end closing (it died or closed us) ends the emulator
            threading.Thread(target=_exit_when_closed, args=(ready, address), daemon=True).start()
        while True:
            try:
                conn = listener.accept()
            except OSError as exc:
                log.warning("DLPC900 emulator: accept failed: %s", exc)
                continue
            if not slots.acquire(blocking=False):
                log.warning("DLPC900 emulator: %d connections already; refused one", MAX_CLIENTS)
                conn.close()
                continue
            threading.Thread(target=_accept, args=(conn, authkey, _Session(backend, lock), slots), daemon=True).start()


def _exit_when_closed(conn, address: str) -> None:
    try:
        conn.recv()
    except (EOFError, OSError):
        pass
    folder = os.path.dirname(address)
    if EMULATOR_DIRS.owner(os.path.basename(folder)) is not None:  # the owner's folder: it may be gone
        shutil.rmtree(folder, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            os.unlink(address)
    os._exit(0)


class EmulatorProcess:
    """The emulator's process, owned by whoever started it (it exits when the owner dies)."""

    def __init__(self, process, conn, address: str, authkey: bytes, tmpdir: str):
        self.process, self._conn = process, conn
        self.address, self.authkey = address, authkey
        self._tmpdir = tmpdir

    @classmethod
    def start(cls, *serials: str, width: int = 1920, height: int = 1080, timeout_s: float = 60.0,
              video_hz: float | None = None) -> "EmulatorProcess":
        EMULATOR_DIRS.sweep()  # the folders of owners that were killed
        tmpdir = os.path.join(EMULATOR_DIRS.directory, EMULATOR_DIRS.new_name())
        address = os.path.join(tmpdir, "usb.sock")
        size = len(os.fsencode(address))
        if size > SOCKET_PATH_MAX:  # the emulator could not bind it: say so now, not after timeout_s
            raise RuntimeError(f"the DLPC900 emulator's socket path {address!r} is {size} bytes, over "
                               f"the {SOCKET_PATH_MAX} a Unix socket address holds: set TMPDIR to a shorter directory")
        os.mkdir(tmpdir, 0o700)  # only this user may reach the socket
        authkey = secrets.token_bytes(16)
        ctx = multiprocessing.get_context("spawn")
        ours, theirs = ctx.Pipe()
        process = ctx.Process(target=serve, name="dpmhw-dlpc900-emulator", daemon=True,
                              args=(address, authkey, serials or ("EMU0001",), width, height, theirs, video_hz))
        try:
            process.start()
            theirs.close()
            try:
                ready = ours.poll(timeout_s) and ours.recv() == "ready"
            except EOFError:
                ready = False  # it died: its error is printed above
            if not ready:
                raise RuntimeError(f"the DLPC900 emulator process did not start within {timeout_s:g} s")
        except BaseException:
            if process.pid is not None:
                process.kill()
                process.join(5)
            ours.close()
            shutil.rmtree(tmpdir, ignore_errors=True)
            raise
        return cls(process, ours, address, authkey, tmpdir)

    def inspect(self) -> list[dict]:
        """Each emulated controller's state as the device holds it (dark, idle, claimed …)."""
        with contextlib.closing(_connect(self.address, self.authkey)) as conn:
            conn.send(("inspect", ()))
            return conn.recv()[1]

    def close(self) -> None:
        self._conn.close()
        self.process.join(5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5)
        shutil.rmtree(self._tmpdir, ignore_errors=True)


def _connect(address: str, authkey: bytes, timeout_s: float = REPLY_TIMEOUT_S) -> Connection:
    """An authenticated connection whose every read and write is bounded by `timeout_s`."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    deadline = time.monotonic() + timeout_s
    try:
        sock.settimeout(timeout_s)
        while True:
            try:
                sock.connect(address)
                break
            except BlockingIOError:  # its accept queue is full (Unix sockets say so at once): retry
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"{address}: no room in the accept queue within {timeout_s:g} s") from None
                time.sleep(0.005)
        sock.settimeout(None)  # blocking again; the bound is SO_RCVTIMEO / SO_SNDTIMEO from here
        conn = Connection(sock.detach())
    finally:
        sock.close()
    try:
        _set_timeout(conn, timeout_s)
        answer_challenge(conn, authkey)
        deliver_challenge(conn, authkey)
    except BaseException:
        conn.close()
        raise
    return conn


# ---- the host side: a pyusb backend ---------------------------------------------------------
class _RemoteDevice:
    def __init__(self, index: int):
        self.index = index


class SocketBackend(usb.backend.IBackend):
    """pyusb backend forwarding every call to an `EmulatorProcess` (one connection, serialised)."""

    def __init__(self, address: str, authkey: bytes):
        super().__init__()
        self.address, self.authkey = address, authkey
        self._lock = threading.Lock()
        self._conn = None

    def _call(self, op: str, *args) -> Any:
        with self._lock:
            try:
                if self._conn is None:
                    self._conn = _connect(self.address, self.authkey)
                self._conn.send((op, args))
                outcome, value = self._conn.recv()
            except (OSError, EOFError) as exc:
                if self._conn is not None:  # a reply may still come: this connection is out of step
                    self._conn.close()
                self._conn = None
                if isinstance(exc, (BlockingIOError, TimeoutError)):  # no answer within REPLY_TIMEOUT_S
                    raise _timeout() from None
                raise _usb_error(errno.ENODEV) from None  # the device is gone (emulator process ended)
        if outcome == "ok":
            return value
        if outcome == "usb":
            timeout, text, code, err = value
            cls = usb.core.USBTimeoutError if timeout else usb.core.USBError
            raise cls(text, code, err)
        name, text = value
        raise (IndexError if name == "IndexError" else RuntimeError)(text)

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def enumerate_devices(self):
        try:
            indices = self._call("enumerate")
        except usb.core.USBError:
            return
        for i in indices:
            yield _RemoteDevice(i)

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return _Desc(**self._call("get_device_descriptor", dev.index))

    def get_configuration_descriptor(self, dev, config):
        return _Desc(**self._call("get_configuration_descriptor", dev.index, config))

    def get_interface_descriptor(self, dev, intf, alt, config):
        return _Desc(**self._call("get_interface_descriptor", dev.index, intf, alt, config))

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        return _Desc(**self._call("get_endpoint_descriptor", dev.index, ep, intf, alt, config))

    def open_device(self, dev):
        return self._call("open_device", dev.index)

    def close_device(self, dev_handle):
        with contextlib.suppress(usb.core.USBError):
            self._call("close_device", dev_handle)

    def set_configuration(self, dev_handle, config_value):
        self._call("set_configuration", dev_handle, config_value)

    def get_configuration(self, dev_handle):
        return self._call("get_configuration", dev_handle)

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._call("set_interface_altsetting", dev_handle, intf, altsetting)

    def claim_interface(self, dev_handle, intf):
        self._call("claim_interface", dev_handle, intf)

    def release_interface(self, dev_handle, intf):
        self._call("release_interface", dev_handle, intf)

    def is_kernel_driver_active(self, dev_handle, intf):
        return self._call("is_kernel_driver_active", dev_handle, intf)

    def detach_kernel_driver(self, dev_handle, intf):
        self._call("detach_kernel_driver", dev_handle, intf)

    def attach_kernel_driver(self, dev_handle, intf):
        self._call("attach_kernel_driver", dev_handle, intf)

    def clear_halt(self, dev_handle, ep):
        self._call("clear_halt", dev_handle, ep)

    def reset_device(self, dev_handle):
        self._call("reset_device", dev_handle)

    def intr_write(self, dev_handle, ep, intf, data, timeout):
        return self._call("intr_write", dev_handle, ep, intf, bytes(data), timeout)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        report = self._call("intr_read", dev_handle, ep, intf, len(buff), timeout)
        buff[: len(report)] = type(buff)("B", report) if hasattr(buff, "typecode") else report
        return len(report)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        if bmRequestType & 0x80:  # device-to-host: the device fills `data`
            blob = self._call("ctrl_transfer", dev_handle, bmRequestType, bRequest, wValue, wIndex, len(data), timeout)
            data[: len(blob)] = type(data)("B", blob) if hasattr(data, "typecode") else blob
            return len(blob)
        return self._call("ctrl_transfer", dev_handle, bmRequestType, bRequest, wValue, wIndex, bytes(data), timeout)


@contextlib.contextmanager
def socket_usb(address: str, authkey: bytes) -> Iterator[SocketBackend]:
    """Put the emulator at `address` on pyusb's default bus for the block (as `usb_emulation()` does)."""
    import usb.backend.libusb0 as libusb0
    import usb.backend.libusb1 as libusb1
    import usb.backend.openusb as openusb

    backend = SocketBackend(address, authkey)
    saved = [(m, m.get_backend) for m in (libusb1, openusb, libusb0)]
    for m, _ in saved:
        m.get_backend = lambda *args, **kwargs: backend
    try:
        yield backend
    finally:
        for m, fn in saved:
            m.get_backend = fn
        backend.close()
