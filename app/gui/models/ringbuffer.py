"""A fixed-size ring buffer of rows, written by a worker thread and read by a GUI timer."""

from __future__ import annotations

import threading

import numpy as np


class RingBuffer:
    """The newest ``capacity`` rows of ``columns`` floats.

    ``extend`` (any thread) appends rows, overwriting the oldest;
    ``snapshot`` (any thread) returns a copy of the rows in time order.
    ``generation`` counts appended rows so a reader can skip redraws when nothing arrived.
    """

    def __init__(self, capacity: int, columns: int):
        self.capacity = int(capacity)
        self.columns = int(columns)
        self._data = np.full((self.capacity, self.columns), np.nan)
        self._next = 0  # index of the next row to write
        self._size = 0
        self.generation = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self._size

    def extend(self, rows) -> None:
        rows = np.asarray(rows, float).reshape(-1, self.columns)
        n = n_in = len(rows)
        if n == 0:
            return
        if n >= self.capacity:
            rows = rows[-self.capacity:]
            n = self.capacity
        with self._lock:
            end = self._next + n
            if end <= self.capacity:
                self._data[self._next:end] = rows
            else:
                k = self.capacity - self._next
                self._data[self._next:] = rows[:k]
                self._data[:n - k] = rows[k:]
            self._next = end % self.capacity
            self._size = min(self.capacity, self._size + n)
            self.generation += n_in

    def append(self, *row: float) -> None:
        self.extend([row])

    def snapshot(self, last: int | None = None) -> np.ndarray:
        """The newest ``last`` rows (all when None), oldest first, as a new array."""
        with self._lock:
            n = self._size if last is None else min(int(last), self._size)
            start = (self._next - n) % self.capacity
            if start + n <= self.capacity:
                return self._data[start:start + n].copy()
            return np.concatenate([self._data[start:], self._data[:self._next]])

    def clear(self) -> None:
        with self._lock:
            self._next = 0
            self._size = 0
            self.generation += 1
