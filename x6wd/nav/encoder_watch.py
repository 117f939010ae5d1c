"""Do the two sides' wheel encoders agree with the compass? A watch over straight driving.

One encoder that stops counting, loses a quadrature channel (half the counts) or counts
backwards (A and B swapped) passes every check of its own: counts keep coming, the wheels'
mean travel is still there. The EKF then takes the two sides' difference for a turn the
body never made (a dead side on a 0.245 m track: 4 rad per metre driven), refuses the
compass that says otherwise, and the failsafe that finally stops the robot named the
compass ("compass untrusted") or the GPS course ("a compass fault?"); on other seeds the
mission completed on the broken odometry without a word (an outside audit, round 5).

The body's turn is what the compass measured, so over a stretch of driving with both
sides commanded the same way (no pivot: a pivot's side difference is the turn, and a
slipping pivot turns the wheels without the body), the sides' travel difference
``D = Σ(s_l − s_r)`` must be the compass's turn ``C`` times an effective track between
``TRACK_SCALE_MIN`` and ``TRACK_SCALE_MAX`` times the configured one (a skid steer's
effective track is 1.2-2x the geometric one, and the configured value may be either). The
residual beyond that range is what the encoders disagree by; over ``WINDOW_M`` of travel a
healthy robot's is a few per cent of it (wheel diameters a few per cent apart, the
non-systematic noise), a dead side's 200 %, a halved side's 67 %, a reversed side's 200 %.
A window in which the compass jumped faster than a body turns (a compass reading random
bearings: the compass watch judges that) or went stale says nothing and starts again.
"""

from __future__ import annotations

import math

from x6wd.core.geodesy import wrap_deg

WINDOW_M = 5.0
"""Travel (m, the mean of the sides' absolute travel) a verdict is taken over."""
DISAGREE_FRACTION = 0.25
"""The residual side difference, as a fraction of the window's travel, that makes the
encoders faulty (healthy: under 0.1 with tyres 10 % apart)..."""
DISAGREE_MIN_M = 0.2
"""... plus this (m): the non-systematic noise of a short window."""
TRACK_SCALE_MIN = 0.5
TRACK_SCALE_MAX = 3.0
"""The effective track the compass's turn is allowed to imply, as multiples of the
configured ``[odometry] track_m`` (uncalibrated: the geometric track, 1.2-2x too small)."""
MAX_COMPASS_STEP_DEG_PER_S = 360.0
"""A compass step faster than this between two samples is no body's turn."""
MAX_COMPASS_STEP_DEG = 120.0
"""A step larger than this between two samples is ambiguous (a slow compass on a fast
turn: 180° one way is 180° the other): the window starts again."""


class EncoderWatch:
    """Fed each wheel increment with the drive command and the compass (sans-IO)."""

    def __init__(self, track_m: float) -> None:
        self.track_m = track_m
        self._reset()

    def _reset(self) -> None:
        self._left_m = 0.0
        self._right_m = 0.0
        self._travel_m = 0.0  # Σ(|s_l| + |s_r|) / 2
        self._turn_rad = 0.0  # the compass's net clockwise turn
        self._prev: tuple[float, float] | None = None  # (t_s, bearing_deg)
        self._drop_pending()

    def _drop_pending(self) -> None:
        # the wheels since the last counted compass sample: they join the window with the
        # turn up to the next sample, and are dropped with it when that turn is lost
        self._pending = (0.0, 0.0, 0.0)  # (left m, right m, travel m)

    def reset(self) -> None:
        """Forget the window (a mission start)."""
        self._reset()

    def on_increment(
        self,
        t_s: float,
        left_m: float,
        right_m: float,
        left_pct: float,
        right_pct: float,
        bearing_deg: float | None,
        bearing_t_s: float | None = None,
    ) -> str:
        """One wheel increment (m per side, signed) ending at ``t_s`` (s), driven by the
        command (left, right %), with the compass's latest bearing (deg; None: none recent)
        and its sample time (s; None: taken as ``t_s``, a sample per increment). The turn
        is counted between the compass's own samples, so a slow compass whose bearing is
        held over several increments still counts (at 1 Hz it counted none: a healthy
        tight circle read as an encoder fault). Returns why the encoders disagree with the
        compass, once per window, else ""."""
        mean_pct = 0.5 * (left_pct + right_pct)
        straight = mean_pct != 0.0 and abs(left_pct - right_pct) <= abs(mean_pct)
        if not straight or bearing_deg is None:
            # a pivot or no compass between: the next sample restarts C, and the wheels
            # since the last sample, whose turn is now lost, leave with it
            self._prev = None
            self._drop_pending()
            return ""
        sample_t = t_s if bearing_t_s is None else bearing_t_s
        prev = self._prev
        if prev is None:
            self._prev = (sample_t, bearing_deg)
            return ""  # the turn before this bearing is unknown: start counting after it
        pl, pr, pt = self._pending
        self._pending = (pl + left_m, pr + right_m, pt + 0.5 * (abs(left_m) + abs(right_m)))
        if sample_t == prev[0]:
            return ""  # the compass's bearing held: judged with its turn at the next sample
        step = wrap_deg(bearing_deg - prev[1])
        dt = sample_t - prev[0]
        if (
            dt <= 0
            or abs(step) > MAX_COMPASS_STEP_DEG_PER_S * max(dt, 0.05)
            or abs(step) > MAX_COMPASS_STEP_DEG
        ):
            self._reset()
            return ""
        self._turn_rad += math.radians(step)
        self._prev = (sample_t, bearing_deg)
        pl, pr, pt = self._pending
        self._drop_pending()
        self._left_m += pl
        self._right_m += pr
        self._travel_m += pt
        full = self._travel_m >= WINDOW_M
        left, right, c, travel = self._left_m, self._right_m, self._turn_rad, self._travel_m
        d = left - right  # Σ(s_l - s_r)
        expected = self.track_m * c
        if expected == 0.0:
            residual = abs(d)
        else:
            k = min(max(d / expected, TRACK_SCALE_MIN), TRACK_SCALE_MAX)
            residual = abs(d - k * expected)
        # judged at every sample against what a whole healthy window may leave, so a gross
        # disagreement (a dead side: 200 %) is named within a metre or two, not after 5 m
        faulty = residual > DISAGREE_FRACTION * max(travel, WINDOW_M) + DISAGREE_MIN_M
        if full or faulty:
            self._reset()
            self._prev = (sample_t, bearing_deg)
        if not faulty:
            return ""
        return (
            f"encoders disagree with the compass: left counted {left:.1f} m, right "
            f"{right:.1f} m on a straight drive while the compass turned "
            f"{math.degrees(c):.0f}° (the wheels say {math.degrees(d / self.track_m):.0f}°): "
            "an encoder failed or miscounts"
        )
