"""Zenoh shared memory for large payloads (images): ``ShmWriter``."""
from __future__ import annotations


class ShmWriter:
    """Puts large payloads into Zenoh shared memory: the receiving processes on this machine
    map them instead of reading them from a socket (remote peers get a copy, transparently).
    Returns None (send normally) when the pool is full, so a slow consumer never blocks us."""

    MIN_BYTES = 1 << 16

    def __init__(self, pool_bytes: int):
        from zenoh import shm
        self._shm = shm
        self.provider = shm.ShmProvider.default_backend(pool_bytes)
        self.failures = 0

    def payload(self, head: bytes, tail):
        buf = self.reserve(len(head), tail)
        return None if buf is None else self.seal(buf, head)

    def reserve(self, head_len: int, tail):
        """A buffer with ``tail`` copied in after ``head_len`` free bytes (None: pool full)."""
        import zenoh
        n = head_len + len(tail)
        try:
            buf = self.provider.alloc(n, self._shm.GarbageCollect())
        except zenoh.ZError:
            self.failures += 1
            return None
        buf[head_len:n] = tail if isinstance(tail, (bytes, bytearray)) else bytes(tail)
        return buf

    @staticmethod
    def seal(buf, head: bytes):
        """The payload of a ``reserve``d buffer once its head is written (the buffer is used up)."""
        import zenoh
        buf[0:len(head)] = head
        return zenoh.ZBytes(buf)
