"""One latest-value slot in shared memory: a single writer process, any number of readers.

The session process publishes its status and its latest frame here; the API process reads them
without ever asking the session for anything, so no request takes the session's interpreter lock.
A sequence lock keeps it wait-free for the writer: the sequence number is odd while a write is in
progress; a reader copies the payload and accepts it only if the sequence was even and unchanged
across the copy (x86-64 and aarch64 Linux: the counter is a naturally aligned 8-byte word).

Header (uint64): sequence, payload length, publish time (time.monotonic_ns, one clock for every
process on the machine), then `META` caller-defined integers.

Each slot is named by its creator's pid (`dpmhw.child_process.SHARED_SLOTS`): the creator removes
it on close, and the slots of a creator that was killed are swept by the supervisor.
"""

from __future__ import annotations

import time
from multiprocessing import shared_memory

import numpy as np

from dpmhw.child_process import SHARED_SLOTS

__all__ = ["SharedSlot", "SlotTornError"]

META = 5
_HEADER = 3 + META  # uint64 words


class SlotTornError(RuntimeError):
    """The writer kept overwriting the slot while it was being read (retried and gave up)."""


class SharedSlot:
    """`SharedSlot.create(capacity)` in the writer; `SharedSlot.attach(name)` in a reader."""

    def __init__(self, shm: shared_memory.SharedMemory, owner: bool):
        self._shm = shm
        self.owner = owner
        self.name = shm.name
        self._header = np.ndarray((_HEADER,), np.uint64, shm.buf, 0)
        self._data = np.ndarray((shm.size - _HEADER * 8,), np.uint8, shm.buf, _HEADER * 8)
        self.capacity = self._data.size

    @classmethod
    def create(cls, capacity: int) -> "SharedSlot":
        shm = shared_memory.SharedMemory(SHARED_SLOTS.new_name(), create=True, size=_HEADER * 8 + int(capacity))
        slot = cls(shm, owner=True)
        slot._header[:] = 0
        return slot

    @classmethod
    def attach(cls, name: str) -> "SharedSlot":
        # Readers are processes the writer spawned: they share its resource tracker, which
        # keeps one registration per name, removed when the creator unlinks the segment.
        return cls(shared_memory.SharedMemory(name=name), owner=False)

    def write(self, payload, meta: tuple[int, ...] = ()) -> None:
        """Publish `payload` (bytes or a uint8 array) with up to `META` non-negative integers."""
        data = np.frombuffer(payload, np.uint8) if isinstance(payload, (bytes, bytearray, memoryview)) \
            else np.asarray(payload, np.uint8).reshape(-1)
        if data.size > self.capacity:
            raise ValueError(f"shared slot {self.name}: payload of {data.size} bytes exceeds its {self.capacity}")
        if len(meta) > META:
            raise ValueError(f"shared slot {self.name}: at most {META} meta values")
        h = self._header
        seq = int(h[0])
        h[0] = seq + 1  # odd: writing
        self._data[:data.size] = data
        h[1] = data.size
        h[2] = time.monotonic_ns()
        h[3:3 + META] = tuple(meta) + (0,) * (META - len(meta))
        h[0] = seq + 2

    def sequence(self) -> int:
        """Changes with every completed write (0: nothing published yet)."""
        return int(self._header[0])

    def read(self, timeout_s: float = 0.05) -> tuple[int, int, tuple[int, ...], bytes] | None:
        """(sequence, publish time ns, meta, payload) of the latest write; None before the first.

        A write in progress is waited out for up to `timeout_s`: a few bare yields, then short
        sleeps (a writer descheduled between its two sequence stores can be gone for milliseconds
        on a loaded machine; bare yields alone can give up and turn /status into a 500)."""
        h = self._header
        deadline = time.monotonic() + timeout_s
        attempt = 0
        while True:
            seq = int(h[0])
            if seq == 0:
                return None
            if seq % 2 == 0:
                length, published = int(h[1]), int(h[2])
                meta = tuple(int(x) for x in h[3:3 + META])
                payload = self._data[:min(length, self.capacity)].tobytes()
                if int(h[0]) == seq:
                    return seq, published, meta, payload
            if time.monotonic() >= deadline:
                break
            attempt += 1
            time.sleep(0 if attempt < 20 else 0.0005)
        raise SlotTornError(f"shared slot {self.name}: still being written after {timeout_s * 1e3:g} ms")

    def close(self) -> None:
        """Detach (the creator also removes the segment)."""
        self._header = self._data = None  # release the buffer views before closing the mapping
        self._shm.close()
        if self.owner:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
