"""A set of sequence numbers kept as sorted closed intervals: received, duplicate and missed counts."""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Sequence


class SeqSet:
    """Distinct non-negative integers as sorted, disjoint, non-adjacent closed intervals ``[lo, hi]``.

    Adding in (nearly) increasing order, the normal case, costs O(log k) for k intervals.
    """

    def __init__(self, ranges: Iterable[Sequence[int]] = ()) -> None:
        self._lo: list[int] = []
        self._hi: list[int] = []
        for lo, hi in sorted((int(a), int(b)) for a, b in ranges):
            if lo < 0 or hi < lo:
                msg = f"invalid sequence range [{lo}, {hi}]"
                raise ValueError(msg)
            if self._hi and lo <= self._hi[-1] + 1:
                self._hi[-1] = max(self._hi[-1], hi)
            else:
                self._lo.append(lo)
                self._hi.append(hi)

    def add(self, seq: int) -> bool:
        """Add ``seq``; True if it was new, False if it was already held (a duplicate)."""
        i = bisect.bisect_right(self._lo, seq) - 1
        if i >= 0 and self._lo[i] <= seq <= self._hi[i]:
            return False
        joins_left = i >= 0 and self._hi[i] == seq - 1
        joins_right = i + 1 < len(self._lo) and self._lo[i + 1] == seq + 1
        if joins_left and joins_right:
            self._hi[i] = self._hi[i + 1]
            del self._lo[i + 1], self._hi[i + 1]
        elif joins_left:
            self._hi[i] = seq
        elif joins_right:
            self._lo[i + 1] = seq
        else:
            self._lo.insert(i + 1, seq)
            self._hi.insert(i + 1, seq)
        return True

    def __contains__(self, seq: object) -> bool:
        if not isinstance(seq, int):
            return False
        i = bisect.bisect_right(self._lo, seq) - 1
        return i >= 0 and self._lo[i] <= seq <= self._hi[i]

    def __len__(self) -> int:
        return sum(h - l + 1 for l, h in zip(self._lo, self._hi, strict=True))

    @property
    def highest(self) -> int:
        """The largest number held, -1 when empty."""
        return self._hi[-1] if self._hi else -1

    def missed(self, start: int = 0) -> int:
        """How many numbers in ``[start, highest]`` are not held (the gaps still open)."""
        if not self._hi:
            return 0
        held = sum(
            min(h, self.highest) - max(l, start) + 1 for l, h in zip(self._lo, self._hi, strict=True) if h >= start
        )
        return max(0, self.highest - start + 1 - held)

    def covers(self, lo: int, hi: int) -> bool:
        """True if every number in ``[lo, hi]`` is held."""
        i = bisect.bisect_right(self._lo, lo) - 1
        return i >= 0 and self._hi[i] >= hi

    def ranges(self) -> list[list[int]]:
        """The intervals as ``[[lo, hi], ...]`` (JSON-ready)."""
        return [[l, h] for l, h in zip(self._lo, self._hi, strict=True)]
