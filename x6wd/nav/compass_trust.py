"""Does the estimator still believe the compass? A watch over the readings it refuses.

A compass that reads a random (valid, in-range) bearing each time passes every check of its
own: the driver sees good registers, the controller a fresh sample. Only the EKF notices:
it gates nearly every reading out (its innovation is far outside the chi-square gate) and
steers on its prediction, nudged by the few that fall inside the gate by chance, so the
robot drives erratically. A healthy compass is refused about 0.1 % of the time (the gate is
at 99.9 %), a knocked-round one for ``compass_recover_after`` readings (the EKF then takes
the new heading: the off-course watch judges that fault), a magnetic disturbance passed
while driving for as long as it lasts. So when :data:`REFUSED_FRACTION` or more of the
readings over a whole window (``[failsafe] compass_refused_s``, 10 s: as long as the stuck
failsafe gives a robot) were refused, the heading is untrusted.
"""

from __future__ import annotations

from collections import deque

REFUSED_FRACTION = 0.5
"""Share of refused readings over the window that makes the compass untrusted. Random
bearings are refused 73-90 % of the time, not all: while the EKF refuses, its heading's
variance grows and so does its gate, and some fall inside it (measured: 10 s windows over
60 s, 10 and 20 Hz, with and without encoders; the audit's robot: 77 %). A healthy compass
is refused about 0.1 %; a disturbance must last half the window to count."""
MIN_READINGS = 20
"""Fewest judged readings in the window for a verdict (a compass read at 2 Hz or slower
says nothing in a short window)."""


class CompassTrust:
    """The refused share of the compass readings over the last ``window_s`` (s), fed one
    judged reading at a time (sans-IO). ``window_s`` 0: never untrusted."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._readings: deque[tuple[float, bool]] = deque()  # (t_s, refused)
        self._refused = 0
        self._first_t: float | None = None  # the first reading (s): a window must pass

    def on_reading(self, t_s: float, refused: bool) -> None:
        """A compass reading at ``t_s`` (s) that the estimator took or ``refused``."""
        if self.window_s <= 0:
            return
        if self._first_t is None:
            self._first_t = t_s
        self._readings.append((t_s, refused))
        self._refused += refused
        self._prune(t_s)

    def verdict(self, t_s: float) -> str:
        """Why the compass is untrusted at ``t_s`` (s) ("the EKF refused 96 % of 200
        readings in 10 s"), or "" while it is trusted or a window has not passed yet."""
        if self._first_t is None or t_s - self._first_t < self.window_s:
            return ""
        self._prune(t_s)
        n = len(self._readings)
        if n < MIN_READINGS or self._refused < REFUSED_FRACTION * n:
            return ""
        return (
            f"the EKF refused {100.0 * self._refused / n:.0f} % of {n} readings "
            f"in {self.window_s:g} s"
        )

    def _prune(self, t_s: float) -> None:
        readings, start = self._readings, t_s - self.window_s
        while readings and readings[0][0] < start:
            self._refused -= readings.popleft()[1]
