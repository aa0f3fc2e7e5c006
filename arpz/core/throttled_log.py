"""Log lines for bad input, at most one per cause per interval.

A hostile or broken peer can send thousands of bad messages a second; one warning (or one
traceback) each filled 20 MB of log in 90 s. Here each cause (a short string such as "undecodable
stats report from robot2") is logged the first time, then at most once per ``interval_s`` with
the number of occurrences since its previous line; the counters that matter are kept elsewhere
(the summary), this only keeps the log readable and small.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

#: the cause that stands for all the others once ``max_causes`` are tracked
OTHER_CAUSES = "(other causes)"


class ThrottledLog:
    def __init__(
        self,
        logger: logging.Logger,
        *,
        interval_s: float = 10.0,
        max_causes: int = 256,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if interval_s <= 0 or max_causes < 1:
            raise ValueError("interval_s must be > 0 and max_causes >= 1")
        self.logger = logger
        self.interval_s = interval_s
        self.max_causes = max_causes
        self._clock = clock
        #: cause -> (when its last line was written, occurrences not logged since)
        self._causes: dict[str, tuple[float, int]] = {}
        self.suppressed = 0

    def log(
        self, level: int, cause: str, message: str, *args: object, exc_info: bool = False
    ) -> bool:
        """Log ``message % args`` unless ``cause`` was logged less than ``interval_s`` ago;
        ``exc_info`` (a traceback) only on the first line of a cause. True if a line was written."""
        now = self._clock()
        if cause not in self._causes and len(self._causes) >= self.max_causes:
            cause = OTHER_CAUSES
        entry = self._causes.get(cause)
        if entry is not None and now - entry[0] < self.interval_s:
            self._causes[cause] = (entry[0], entry[1] + 1)
            self.suppressed += 1
            return False
        first = entry is None
        if entry is not None and entry[1]:
            message += " (and %d more like it in the last %.0f s)"
            args = (*args, entry[1], now - entry[0])
        self._causes[cause] = (now, 0)
        self.logger.log(level, message, *args, exc_info=exc_info and first)
        return True

    def warning(self, cause: str, message: str, *args: object) -> bool:
        return self.log(logging.WARNING, cause, message, *args)

    def exception(self, cause: str, message: str, *args: object) -> bool:
        return self.log(logging.ERROR, cause, message, *args, exc_info=True)
