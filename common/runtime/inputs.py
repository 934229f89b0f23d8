"""A node's pending input messages: ``InputQueue`` (newest-only and keep-all inputs)."""
from __future__ import annotations

import collections
import threading
from typing import Any, Iterable, Optional

KEEP_ALL_LIMIT = 1000          # a KEEP_ALL input queues at most this many (then drops the oldest)


class InputQueue:
    """Pending input messages of one node, in arrival order.

    A newest-only input holds at most one pending payload: a newer one replaces it (``dropped``
    counts the replaced ones). A keep-all input queues every payload (up to ``limit``).
    """

    def __init__(self, keep_all: Iterable[str] = (), limit: int = KEEP_ALL_LIMIT):
        self.keep_all = set(keep_all)
        self.limit = limit
        self._cv = threading.Condition()
        self._order: collections.deque = collections.deque()     # input names, FIFO
        self._latest: dict[str, Any] = {}
        self._queues: dict[str, collections.deque] = collections.defaultdict(collections.deque)
        self.dropped: collections.Counter = collections.Counter()
        self.closed = False

    def put(self, name: str, item) -> None:
        with self._cv:
            if name in self.keep_all:
                q = self._queues[name]
                if len(q) >= self.limit:
                    q.popleft()
                    self._order.remove(name)
                    self.dropped[name] += 1
                q.append(item)
                self._order.append(name)
            else:
                if name in self._latest:
                    self.dropped[name] += 1
                else:
                    self._order.append(name)
                self._latest[name] = item
            self._cv.notify()

    def get(self, timeout: Optional[float] = None):
        """The next ``(name, item)``, or None on timeout or when closed."""
        with self._cv:
            if not self._order and not self.closed:
                self._cv.wait(timeout)
            if not self._order:
                return None
            name = self._order.popleft()
            if name in self.keep_all:
                return name, self._queues[name].popleft()
            return name, self._latest.pop(name)

    def __len__(self):
        with self._cv:
            return len(self._order)

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()
