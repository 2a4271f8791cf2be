"""Seeded random streams of the error model: one independent stream per random effect.

Every stream is a child of ``numpy.random.SeedSequence(seed)`` at a fixed spawn index, so
switching one random effect off leaves the draws of the others unchanged, and a model built with
the same seed repeats its output exactly. Per-session draws (session offsets) come from
``SeedSequence([seed, tag, session])``, so they do not depend on the order sessions are visited.
"""
from __future__ import annotations

import numpy as np

__all__ = ["NormalStream", "normal_stream", "session_rng", "STREAM_INDEX", "SESSION_OFFSET_TAG"]

#: Spawn index of each named stream. Append new streams; never renumber (that would change every
#: seeded output of the effects already using them).
STREAM_INDEX = {"white": 0, "pink": 1, "walk": 2}
#: Tag mixed into the per-session seed of the ``session_offset`` draws.
SESSION_OFFSET_TAG = 0x5E55
#: Normal deviates drawn per refill of a stream's buffer (the single-sample path takes them from it).
_NORMAL_BLOCK = 4096


class NormalStream:
    """Standard-normal deviates of one seeded stream, drawn from the generator in blocks.

    Taking ``n`` values gives exactly the next ``n`` values of ``rng.standard_normal`` whatever
    the chunking (numpy draws them one after another), so the single-sample and vector paths
    consume one identical sequence; blocks only amortise the per-call numpy overhead.
    """

    __slots__ = ("_rng", "_buf", "_i")

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._buf: list[float] = []
        self._i = 0

    def take(self, n: int) -> list[float]:
        """The next ``n`` deviates as a list of floats."""
        i = self._i
        j = i + n
        if j <= len(self._buf):
            self._i = j
            return self._buf[i:j]
        head = self._buf[i:]
        need = n - len(head)
        if need > _NORMAL_BLOCK:
            self._buf, self._i = [], 0
            return head + self._rng.standard_normal(need).tolist()
        self._buf = self._rng.standard_normal(_NORMAL_BLOCK).tolist()
        self._i = need
        return head + self._buf[:need]

    def take_array(self, n: int) -> np.ndarray:
        """The next ``n`` deviates as an array (n,)."""
        rest = len(self._buf) - self._i
        if n <= rest:
            return np.array(self.take(n), dtype=float)
        head = np.array(self._buf[self._i:], dtype=float)
        self._buf, self._i = [], 0
        return np.concatenate([head, self._rng.standard_normal(n - rest)])


def normal_stream(seed: int, name: str) -> NormalStream:
    """The stream ``name`` (a key of :data:`STREAM_INDEX`) of a model seeded with ``seed``, from its start.

    Equal to child ``STREAM_INDEX[name]`` of ``SeedSequence(seed).spawn(...)``.
    """
    seq = np.random.SeedSequence(seed, spawn_key=(STREAM_INDEX[name],))
    return NormalStream(np.random.default_rng(seq))


def session_rng(seed: int, tag: int, session: int) -> np.random.Generator:
    """A generator for one session's draws of one effect (``tag``), independent of visiting order."""
    return np.random.default_rng(np.random.SeedSequence([seed, tag, int(session) % (1 << 63)]))
