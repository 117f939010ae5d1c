"""Composable error layers with physical parameters (used by the simulator AND by x6wd.gap).

INTERFACE (fixed; implementations are filled in below it):

- :class:`PositionSeries`: a time series of position ERRORS or positions in a local
  east/north/up frame (metres), with a per-epoch ``valid`` mask (False = no fix).
- :class:`HeadingSeries`: compass samples: measured heading, pitch, roll (deg), with the
  true heading and the true tilt used by the compass layers.
- An effect is a frozen dataclass with a class attribute ``name`` (one of ``EFFECT_NAMES``)
  and ``apply(series, rng) -> series`` returning a NEW series (inputs are never modified).
  Parameters keep their meaning at any sample rate (e.g. Gauss-Markov uses tau_s, sigma_m
  and the exact discretisation phi = exp(-dt/tau)).
- ``EFFECTS``: name -> effect class, so the gap tool can construct effects by name and
  write them into a simulator config fragment (``to_params()`` / ``from_params()``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

GPS_EFFECT_NAMES = (
    "gauss_markov",
    "random_walk",
    "bias",
    "quantization",
    "jumps",
    "outages",
    "latency",
    "multipath_zone",
)
COMPASS_EFFECT_NAMES = ("hard_iron", "soft_iron", "tilt", "declination", "heading_lag")
EFFECT_NAMES = GPS_EFFECT_NAMES + COMPASS_EFFECT_NAMES


@dataclass(frozen=True)
class PositionSeries:
    """Positions (or position errors) in a local tangent frame, metres.

    ``t_s`` strictly increasing seconds; ``east_m``/``north_m``/``up_m`` same length;
    ``valid`` False where the receiver had no fix (values there are meaningless).
    ``origin_lat_deg``/``origin_lon_deg`` place the frame (needed by quantisation,
    which acts on NMEA minutes). ``speed_mps``/``course_deg`` of the TRUE motion are
    optional (latency and the gap tool's error-vs-speed use them).
    ``nsats`` optional satellites-used count (jumps at satellite-set changes).
    """

    t_s: np.ndarray
    east_m: np.ndarray
    north_m: np.ndarray
    up_m: np.ndarray
    valid: np.ndarray
    origin_lat_deg: float = 0.0
    origin_lon_deg: float = 0.0
    speed_mps: np.ndarray | None = None
    course_deg: np.ndarray | None = None
    nsats: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def with_(self, **changes: object) -> PositionSeries:
        """Copy with some arrays replaced."""
        return replace(self, **changes)  # type: ignore[arg-type]


@dataclass(frozen=True)
class HeadingSeries:
    """Compass samples, degrees. ``heading_deg`` is the MEASURED magnetic heading 0..360;
    ``true_heading_deg`` the truth (if known); pitch/roll measured (deg)."""

    t_s: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    true_heading_deg: np.ndarray | None = None
    field_ut: np.ndarray | None = None  # measured field magnitude (microtesla), if known
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def with_(self, **changes: object) -> HeadingSeries:
        return replace(self, **changes)  # type: ignore[arg-type]
