"""Messages that never arrived, counted from their writers' publication sequence numbers (no
rclpy). rclpy's message info carries the number each DDS writer gives its messages (1, 2, ...);
a reader that got 4 after 1 missed 2 and 3, whether the middleware said so or not (a reliable
KEEP_LAST queue that overflows says nothing). The info does not say which writer a message
came from: the count is exact for a stream with one writer. A number at or below the last one
is a new writer (a restarted publisher) and starts the count afresh. Messages lost after the
last one received leave no gap to count.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Hashable

__all__ = ['SequenceGaps']


class SequenceGaps:
    """Per stream (any key): the last sequence number seen and the messages missed."""

    def __init__(self) -> None:
        self.last: dict[Hashable, int] = {}
        self.missed: Counter = Counter()

    def seen(self, key: Hashable, sequence: int) -> None:
        """A message of stream `key` with this publication sequence number arrived."""
        before = self.last.get(key)
        if before is not None and sequence > before + 1:
            self.missed[key] += sequence - before - 1
        self.last[key] = sequence
