"""A reentrant lock that serves waiters in arrival order.

The training loop holds the trainer's lock over each step and takes it again microseconds after letting go. With
a plain lock the thread that just released usually wins that race, so a viewer waiting to render could wait for
the whole run; here a thread that asks while another waits queues behind it, so a frame gets the next turn.
"""
from __future__ import annotations

import collections
import threading


class TurnLock:
    def __init__(self):
        self._cond = threading.Condition(threading.Lock())
        self._owner = None
        self._depth = 0
        self._queue = collections.deque()

    def acquire(self) -> bool:
        me = threading.get_ident()
        with self._cond:
            if self._owner == me:
                self._depth += 1
                return True
            ticket = object()
            self._queue.append(ticket)
            while self._owner is not None or self._queue[0] is not ticket:
                self._cond.wait()
            self._queue.popleft()
            self._owner, self._depth = me, 1
            return True

    def release(self) -> None:
        with self._cond:
            if self._owner != threading.get_ident():
                raise RuntimeError("TurnLock.release: not held by this thread")
            self._depth -= 1
            if self._depth == 0:
                self._owner = None
                self._cond.notify_all()

    def locked(self) -> bool:
        return self._owner is not None

    __enter__ = acquire

    def __exit__(self, *exc) -> bool:
        self.release()
        return False
