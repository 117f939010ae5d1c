"""A log that keeps storms out: one record per kind of event per period, the rest counted."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any


class RateLimitedLog:
    """At most one log record per key per ``period_s``; the others are counted and reported
    as "N more" with the next record of that key, or by :meth:`flush` once the period is over.
    Keys are a small fixed set (kinds of event), so the table stays small."""

    def __init__(
        self,
        logger: logging.Logger,
        period_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._logger = logger
        self._period_s = period_s
        self._clock = clock
        # key -> [time of the last record (s), suppressed since, level]
        self._state: dict[str, list[Any]] = {}

    def log(self, key: str, level: int, msg: str, *args: Any) -> bool:
        """Log ``msg % args`` unless ``key`` was logged less than a period ago; True if logged."""
        now = self._clock()
        st = self._state.get(key)
        if st is not None and now - st[0] < self._period_s:
            st[1] += 1
            return False
        if st is not None and st[1]:
            msg += " (and %d more in the last %.1f s)"
            args = (*args, st[1], now - st[0])
        self._state[key] = [now, 0, level]
        self._logger.log(level, msg, *args)
        return True

    def flush(self) -> None:
        """Report the suppressed counts whose period is over (a storm that has stopped)."""
        now = self._clock()
        for key, st in self._state.items():
            if st[1] and now - st[0] >= self._period_s:
                self._logger.log(st[2], "%s: %d more in the last %.1f s", key, st[1], now - st[0])
                st[0], st[1] = now, 0
