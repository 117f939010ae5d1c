"""Atmosphere at GPS L1: ionospheric and tropospheric delay, attenuation, received power, SNR.

PUBLIC API (every method is vectorised: array arguments broadcast against each other; the
result has the broadcast shape; scalars give 0-d arrays)

- ``Atmosphere`` (frozen dataclass; validated by ``x6wd.core.config.build`` under ``[atmosphere]``)
    - ``iono_delay_m(el_deg)``: seed formula ``0.162·(1 + 2.74e-6·(96 − e)³)·TEC`` (m).
    - ``tropo_delay_m(el_deg, lat_deg, doy, height_m)``: Saastamoinen hydrostatic zenith delay
      at the receiver height times the Niell hydrostatic mapping (Marini form, seasonal table,
      height correction); plus, only if ``wet_delay`` is true, a Saastamoinen wet zenith delay
      from the water-vapour density times the Niell wet mapping (the seed takes the wet part
      as 0, so it is off by default). Metres.
    - ``zenith_hydrostatic_delay_m(lat_deg, height_m)`` / ``zenith_wet_delay_m()`` (m).
    - ``attenuation_db(el_deg, height_m=0.0)``: total slant-path attenuation (dB) of oxygen,
      water vapour, cloud and rain; ``attenuation_parts_db`` gives each part separately.
    - ``received_power_dbw(el_deg, extra_loss_db=0.0, height_m=0.0)``: P_rec (dBW).
    - ``noise_density_dbwhz``: thermal −204 dBW/Hz + receiver noise figure + environment noise.
    - ``snr_dbhz(el_deg, extra_loss_db=0.0, height_m=0.0)``: C/N0 = P_rec − N0 (dB-Hz).
    - ``usable(snr_dbhz)``: bool array, ``snr >= snr_cutoff_dbhz``.
- Module functions ``marini(sin_el, a, b, c)``, ``niell_hydrostatic_mapping(el_deg, lat_deg,
  doy, height_m)``, ``niell_wet_mapping(el_deg, lat_deg)``, ``slant_path_m(el_deg, h0_m, h1_m,
  h_rx_m)``, ``CLOUD_TYPES``.

Model choices (where the seed is silent):
- Received power: the IS-GPS-200 minimum -158.5 dBW (L1 C/A, at 5° elevation) rising linearly
  in sin(elevation) to ``zenith_gain_db`` more at zenith (satellite beam shaping plus a patch
  antenna's gain toward zenith); below 5° it keeps falling along the same line.
- Gases: simplified ITU-R P.676 (Annex 2) specific attenuation at sea level for the given
  pressure, temperature and water-vapour density, scaled with height by the equivalent
  concentration ``k = exp(−g·m·h/(R·T))`` (dry air, scale height ≈ 8.4 km) for oxygen; water
  vapour falls off faster in the real atmosphere, so it uses ``water_vapour_scale_height_m``.
  The path is integrated through spherical shells (troposphere .. thermosphere) with
  Gauss-Legendre nodes in height, so low elevations see the long slant path.
- Clouds: a uniform layer of liquid water between base and top heights (defaults per type in
  ``CLOUD_TYPES``), ITU-R P.840 Rayleigh attenuation with the double-Debye permittivity at 0 °C.
- Rain: ITU-R P.838 coefficients (circular polarisation, log-interpolated between 1 and 2 GHz)
  from the ground to ``rain_height_m``.
All of it is a few hundredths of a dB at L1, as it should be; SNR is dominated by elevation,
environment noise and reflections.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from x6wd.core.errors import ConfigError

F_L1_GHZ = 1.57542
EARTH_RADIUS_M = 6371.0e3
THERMAL_NOISE_DBWHZ = -204.0  # kT at 290 K
P_MIN_DBW = -158.5  # IS-GPS-200 minimum received L1 C/A power at 5 deg elevation
G_MPS2 = 9.80665
M_AIR_KGPMOL = 0.0289644
R_JPMOLK = 8.314462618
MIN_MAPPING_EL_DEG = 0.5  # mapping functions are evaluated at no lower elevation

# Spherical-shell layers (name, bottom m, top m) the slant path is integrated through.
LAYERS: tuple[tuple[str, float, float], ...] = (
    ("troposphere", 0.0, 11.0e3),
    ("stratosphere", 11.0e3, 50.0e3),
    ("mesosphere", 50.0e3, 85.0e3),
    ("thermosphere", 85.0e3, 600.0e3),
)

# Cloud type -> (liquid water content g/m^3, base height m, top height m); typical values.
CLOUD_TYPES: dict[str, tuple[float, float, float]] = {
    "none": (0.0, 0.0, 0.0),
    "fog": (0.15, 0.0, 100.0),
    "stratus": (0.3, 300.0, 1000.0),
    "stratocumulus": (0.4, 600.0, 1600.0),
    "cumulus": (0.5, 1000.0, 3000.0),
    "nimbostratus": (0.6, 800.0, 4000.0),
    "thunderstorm": (2.0, 1000.0, 10000.0),
}


def _rng(lo: float | None = None, hi: float | None = None, **kw: Any) -> dict[str, Any]:
    return {"min": lo, "max": hi, **kw}


def _arr(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=float)


def marini(sin_el: Any, a: Any, b: Any, c: Any) -> np.ndarray:
    """Marini continued fraction normalised to 1 at zenith (dimensionless)."""
    top = 1.0 + a / (1.0 + b / (1.0 + c))
    return np.asarray(top / (sin_el + a / (sin_el + b / (sin_el + c))))


# Niell hydrostatic table: |lat| deg, then a,b,c averages and a,b,c amplitudes.
_NIELL_LAT = np.array([15.0, 30.0, 45.0, 60.0, 75.0])
_NIELL_AVG = np.array(
    [
        [1.2769934e-3, 2.9153695e-3, 62.610505e-3],
        [1.2683230e-3, 2.9152299e-3, 62.837393e-3],
        [1.2465397e-3, 2.9288445e-3, 63.721774e-3],
        [1.2196049e-3, 2.9022565e-3, 63.824265e-3],
        [1.2045996e-3, 2.9024912e-3, 64.258455e-3],
    ]
)
_NIELL_AMP = np.array(
    [
        [0.0, 0.0, 0.0],
        [1.2709626e-5, 2.1414979e-5, 9.0128400e-5],
        [2.6523662e-5, 3.0160779e-5, 4.3497037e-5],
        [3.4000452e-5, 7.2562722e-5, 84.795348e-5],
        [4.1202191e-5, 11.723375e-5, 170.37206e-5],
    ]
)
_NIELL_WET = np.array(
    [
        [5.8021897e-4, 1.4275268e-3, 4.3472961e-2],
        [5.6794847e-4, 1.5138625e-3, 4.6729510e-2],
        [5.8118019e-4, 1.4572752e-3, 4.3908931e-2],
        [5.9727542e-4, 1.5007428e-3, 4.4626982e-2],
        [6.1641693e-4, 1.7599082e-3, 5.4736038e-2],
    ]
)
_A_HT, _B_HT, _C_HT = 2.53e-5, 5.49e-3, 1.14e-3
_T0_DOY = 28.0
_YEAR_D = 365.25


def _interp_lat(abs_lat: np.ndarray, table: np.ndarray, col: int) -> np.ndarray:
    # np.interp clamps outside 15..75 deg, which is Niell's own convention.
    return np.interp(abs_lat, _NIELL_LAT, table[:, col])


def niell_hydrostatic_mapping(el_deg: Any, lat_deg: Any, doy: Any, height_m: Any) -> np.ndarray:
    """Niell hydrostatic mapping function (dimensionless, ≈1 at zenith, ≈10 at 5°).

    ``doy`` is the day of year (1..366, fractional allowed); the southern hemisphere is
    shifted by half a year; ``height_m`` is the receiver height above sea level.
    Elevations below ``MIN_MAPPING_EL_DEG`` are evaluated at that floor.
    """
    # Niell is fitted down to 3 deg; below that it is only extrapolated, and at 0 deg the
    # height term diverges, so elevations are floored at MIN_MAPPING_EL_DEG.
    el = np.radians(np.maximum(_arr(el_deg), MIN_MAPPING_EL_DEG))
    lat = _arr(lat_deg)
    t = _arr(doy) + np.where(lat < 0.0, _YEAR_D / 2.0, 0.0)
    abs_lat = np.abs(lat)
    season = np.cos(2.0 * np.pi * (t - _T0_DOY) / _YEAR_D)
    a, b, c = (
        _interp_lat(abs_lat, _NIELL_AVG, i) - _interp_lat(abs_lat, _NIELL_AMP, i) * season
        for i in range(3)
    )
    sin_el = np.sin(el)
    m = marini(sin_el, a, b, c)
    m_ht = marini(sin_el, _A_HT, _B_HT, _C_HT)
    return m + (1.0 / sin_el - m_ht) * (_arr(height_m) / 1000.0)


def niell_wet_mapping(el_deg: Any, lat_deg: Any) -> np.ndarray:
    """Niell wet mapping function (dimensionless; no seasonal or height term)."""
    abs_lat = np.abs(_arr(lat_deg))
    a, b, c = (_interp_lat(abs_lat, _NIELL_WET, i) for i in range(3))
    return marini(np.sin(np.radians(np.maximum(_arr(el_deg), MIN_MAPPING_EL_DEG))), a, b, c)


def slant_path_m(el_deg: Any, h0_m: Any, h1_m: Any, h_rx_m: Any = 0.0) -> np.ndarray:
    """Length (m) of the straight slant path inside the spherical shell h0..h1 above sea level,
    from a receiver at ``h_rx_m`` at elevation ``el_deg`` (parts of the shell below the receiver
    are not on the path)."""
    r_rx = EARTH_RADIUS_M + _arr(h_rx_m)
    el = np.radians(np.maximum(_arr(el_deg), 0.0))
    cos2 = (r_rx * np.cos(el)) ** 2
    sin_term = r_rx * np.sin(el)

    def reach(h: Any) -> np.ndarray:
        r = EARTH_RADIUS_M + np.maximum(_arr(h), _arr(h_rx_m))
        return np.sqrt(np.maximum(r * r - cos2, 0.0)) - sin_term

    return np.maximum(reach(h1_m) - reach(h0_m), 0.0)


def _phi(rp: float, rt: float, a: float, b: float, c: float, d: float) -> float:
    return float(rp**a * rt**b * math.exp(c * (1.0 - rp) + d * (1.0 - rt)))


def oxygen_specific_db_per_km(f_ghz: float, pressure_hpa: float, temperature_k: float) -> float:
    """Simplified ITU-R P.676 (Annex 2) dry-air specific attenuation below 54 GHz (dB/km)."""
    rp = pressure_hpa / 1013.0
    rt = 288.0 / temperature_k
    xi1 = _phi(rp, rt, 0.0717, -1.8132, 0.0156, -1.6515)
    xi2 = _phi(rp, rt, 0.5146, -4.6368, -0.1921, -5.7416)
    xi3 = _phi(rp, rt, 0.3414, -6.5851, 0.2130, -8.5854)
    f2 = f_ghz * f_ghz
    g = 7.2 * rt**2.8 / (f2 + 0.34 * rp**2 * rt**1.6) + 0.62 * xi3 / (
        (54.0 - f_ghz) ** (1.16 * xi1) + 0.83 * xi2
    )
    return g * f2 * rp**2 * 1e-3


def water_vapour_specific_db_per_km(
    f_ghz: float, pressure_hpa: float, temperature_k: float, rho_gm3: float
) -> float:
    """Simplified ITU-R P.676 (Annex 2) water-vapour specific attenuation (dB/km)."""
    if rho_gm3 <= 0.0:
        return 0.0
    rp = pressure_hpa / 1013.0
    rt = 288.0 / temperature_k
    eta1 = 0.955 * rp * rt**0.68 + 0.006 * rho_gm3
    eta2 = 0.735 * rp * rt**0.5 + 0.0353 * rt**4 * rho_gm3

    def g(fi: float) -> float:
        return 1.0 + ((f_ghz - fi) / (f_ghz + fi)) ** 2

    f = f_ghz
    s = (
        3.98 * eta1 * math.exp(2.23 * (1 - rt)) / ((f - 22.235) ** 2 + 9.42 * eta1**2) * g(22.0)
        + 11.96 * eta1 * math.exp(0.7 * (1 - rt)) / ((f - 183.31) ** 2 + 11.14 * eta1**2)
        + 0.081 * eta1 * math.exp(6.44 * (1 - rt)) / ((f - 321.226) ** 2 + 6.29 * eta1**2)
        + 3.66 * eta1 * math.exp(1.6 * (1 - rt)) / ((f - 325.153) ** 2 + 9.22 * eta1**2)
        + 25.37 * eta1 * math.exp(1.09 * (1 - rt)) / (f - 380.0) ** 2
        + 17.4 * eta1 * math.exp(1.46 * (1 - rt)) / (f - 448.0) ** 2
        + 844.6 * eta1 * math.exp(0.17 * (1 - rt)) / (f - 557.0) ** 2 * g(557.0)
        + 290.0 * eta1 * math.exp(0.41 * (1 - rt)) / (f - 752.0) ** 2 * g(752.0)
        + 8.3328e4 * eta2 * math.exp(0.99 * (1 - rt)) / (f - 1780.0) ** 2 * g(1780.0)
    )
    return s * f * f * rt**2.5 * rho_gm3 * 1e-4


def cloud_specific_coefficient(f_ghz: float, temperature_k: float = 273.15) -> float:
    """ITU-R P.840 liquid-water specific attenuation coefficient K_l ((dB/km)/(g/m^3))."""
    theta = 300.0 / temperature_k
    eps0 = 77.66 + 103.3 * (theta - 1.0)
    eps1 = 0.0671 * eps0
    eps2 = 3.52
    fp = 20.20 - 146.0 * (theta - 1.0) + 316.0 * (theta - 1.0) ** 2
    fs = 39.8 * fp
    f = f_ghz
    eps_im = f * (eps0 - eps1) / (fp * (1 + (f / fp) ** 2)) + f * (eps1 - eps2) / (
        fs * (1 + (f / fs) ** 2)
    )
    eps_re = (eps0 - eps1) / (1 + (f / fp) ** 2) + (eps1 - eps2) / (1 + (f / fs) ** 2) + eps2
    eta = (2.0 + eps_re) / eps_im
    return 0.819 * f / (eps_im * (1.0 + eta * eta))


def rain_coefficients(f_ghz: float) -> tuple[float, float]:
    """ITU-R P.838 (k, alpha) for circular polarisation, log-interpolated in 1..2 GHz."""
    # (k_H, alpha_H, k_V, alpha_V) at 1 GHz and 2 GHz.
    k_h1, a_h1, k_v1, a_v1 = 0.0000259, 0.9691, 0.0000308, 0.8592
    k_h2, a_h2, k_v2, a_v2 = 0.0000847, 1.0664, 0.0000998, 0.9490
    w = math.log10(f_ghz)  # fraction between log10(1)=0 and log10(2)
    w /= math.log10(2.0)

    def lerp_log(k1: float, k2: float) -> float:
        return 10 ** (math.log10(k1) + w * (math.log10(k2) - math.log10(k1)))

    k_h, k_v = lerp_log(k_h1, k_h2), lerp_log(k_v1, k_v2)
    a_h, a_v = a_h1 + w * (a_h2 - a_h1), a_v1 + w * (a_v2 - a_v1)
    k = (k_h + k_v) / 2.0
    alpha = (k_h * a_h + k_v * a_v) / (2.0 * k)
    return k, alpha


# Gauss-Legendre nodes per layer for the slant-path integral of height-dependent attenuation.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(12)
# Elevation grid for the cached attenuation table (deg).
_TABLE_EL_DEG = np.concatenate([np.linspace(0.0, 10.0, 201), np.linspace(10.05, 90.0, 400)])


@dataclass(frozen=True)
class Atmosphere:
    """Physical parameters of the atmosphere and the radio environment of one scenario."""

    tec_tecu: float = field(default=17.0, metadata=_rng(0.0, 500.0))  # 1 TECU = 1e16 e/m^2
    temperature_k: float = field(default=288.15, metadata=_rng(200.0, 340.0))  # at sea level
    pressure_hpa: float = field(default=1013.25, metadata=_rng(500.0, 1100.0))  # at sea level
    water_vapour_gm3: float = field(default=7.5, metadata=_rng(0.0, 50.0))  # at sea level
    water_vapour_scale_height_m: float = field(default=2000.0, metadata=_rng(100.0, 20000.0))
    wet_delay: bool = False  # seed: wet zenith delay taken as 0
    cloud: str = field(default="none", metadata={"choices": tuple(CLOUD_TYPES)})
    cloud_lwc_gm3: float | None = field(default=None, metadata=_rng(0.0, 10.0))
    cloud_base_m: float | None = field(default=None, metadata=_rng(0.0, 20000.0))
    cloud_top_m: float | None = field(default=None, metadata=_rng(0.0, 20000.0))
    rain_mmph: float = field(default=0.0, metadata=_rng(0.0, 500.0))
    rain_height_m: float = field(default=3000.0, metadata=_rng(0.0, 10000.0))
    env_noise_db: float = field(default=1.0, metadata=_rng(0.0, 60.0))  # 1 country, 40 industry
    noise_figure_db: float = field(default=2.0, metadata=_rng(0.0, 20.0))  # receiver front end
    p_min_dbw: float = field(default=P_MIN_DBW, metadata=_rng(-200.0, -100.0))
    zenith_gain_db: float = field(default=5.0, metadata=_rng(0.0, 20.0))
    snr_cutoff_dbhz: float = field(default=15.0, metadata=_rng(0.0, 60.0))

    def __post_init__(self) -> None:
        if self.cloud not in CLOUD_TYPES:
            raise ConfigError(
                f"atmosphere.cloud: must be one of {', '.join(CLOUD_TYPES)}, got {self.cloud!r}"
            )
        base, top = self.cloud_layer_m()
        if top < base:
            raise ConfigError(
                f"atmosphere.cloud_top_m: must be >= cloud_base_m ({base} m), got {top} m"
            )
        for name in ("tec_tecu", "water_vapour_gm3", "rain_mmph", "temperature_k"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0.0:
                raise ConfigError(f"atmosphere.{name}: must be finite and >= 0, got {value!r}")

    # ------------------------------------------------------------------ delays
    def iono_delay_m(self, el_deg: Any) -> np.ndarray:
        """Ionospheric group delay (m) at elevation ``el_deg`` (seed formula)."""
        e = _arr(el_deg)
        return 0.162 * (1.0 + 2.74e-6 * (96.0 - e) ** 3) * self.tec_tecu

    def zenith_hydrostatic_delay_m(self, lat_deg: Any, height_m: Any) -> np.ndarray:
        """Saastamoinen hydrostatic zenith delay (m) with a standard-atmosphere pressure at
        ``height_m`` above sea level (≈2.3 m at sea level)."""
        h = _arr(height_m)
        p_hpa = self.pressure_hpa * (1.0 - 2.2557e-5 * h) ** 5.2568
        lat = np.radians(_arr(lat_deg))
        return 0.0022768 * p_hpa / (1.0 - 0.00266 * np.cos(2.0 * lat) - 0.00028 * h / 1000.0)

    def zenith_wet_delay_m(self) -> float:
        """Saastamoinen wet zenith delay (m) from the sea-level water-vapour density."""
        e_hpa = self.water_vapour_gm3 * self.temperature_k / 216.7
        return 0.002277 * (1255.0 / self.temperature_k + 0.05) * e_hpa

    def tropo_delay_m(self, el_deg: Any, lat_deg: Any, doy: Any, height_m: Any = 0.0) -> np.ndarray:
        """Tropospheric slant delay (m): zenith hydrostatic delay × Niell hydrostatic mapping
        (+ wet part when ``wet_delay``). ``doy`` day of year, ``height_m`` above sea level."""
        zhd = self.zenith_hydrostatic_delay_m(lat_deg, height_m)
        delay = zhd * niell_hydrostatic_mapping(el_deg, lat_deg, doy, height_m)
        if self.wet_delay:
            delay = delay + self.zenith_wet_delay_m() * niell_wet_mapping(el_deg, lat_deg)
        return np.asarray(delay)

    # ------------------------------------------------------------- attenuation
    def cloud_layer_m(self) -> tuple[float, float]:
        """(base, top) of the cloud layer in metres above sea level."""
        _lwc, base, top = CLOUD_TYPES[self.cloud]
        return (
            base if self.cloud_base_m is None else self.cloud_base_m,
            top if self.cloud_top_m is None else self.cloud_top_m,
        )

    def cloud_lwc(self) -> float:
        """Liquid water content of the cloud layer (g/m^3); 0 without clouds."""
        if self.cloud == "none" and self.cloud_lwc_gm3 is None:
            return 0.0
        return CLOUD_TYPES[self.cloud][0] if self.cloud_lwc_gm3 is None else self.cloud_lwc_gm3

    def attenuation_parts_db(self, el_deg: Any, height_m: float = 0.0) -> dict[str, np.ndarray]:
        """Slant-path attenuation (dB) per cause: keys ``oxygen``, ``water_vapour``, ``cloud``,
        ``rain`` and, for the gases, per layer ``oxygen:troposphere`` etc."""
        el = _arr(el_deg)
        table = _attenuation_table(self, float(height_m))
        return {k: np.interp(el, _TABLE_EL_DEG, v) for k, v in table.items()}

    def attenuation_db(self, el_deg: Any, height_m: float = 0.0) -> np.ndarray:
        """Total slant-path attenuation (dB) of gases, cloud and rain at L1."""
        el = _arr(el_deg)
        table = _attenuation_table(self, float(height_m))
        return np.interp(el, _TABLE_EL_DEG, table["total"])

    # ------------------------------------------------------------ power, SNR
    @property
    def noise_density_dbwhz(self) -> float:
        """Noise power density N0 (dBW/Hz): thermal + receiver noise figure + environment."""
        return THERMAL_NOISE_DBWHZ + self.noise_figure_db + self.env_noise_db

    def received_power_dbw(
        self, el_deg: Any, extra_loss_db: Any = 0.0, height_m: float = 0.0
    ) -> np.ndarray:
        """Received L1 C/A power (dBW): the elevation pattern minus atmospheric attenuation
        minus ``extra_loss_db`` (e.g. 3 dB per reflection)."""
        el = _arr(el_deg)
        s5 = math.sin(math.radians(5.0))
        pattern = self.zenith_gain_db * (np.sin(np.radians(el)) - s5) / (1.0 - s5)
        return self.p_min_dbw + pattern - self.attenuation_db(el, height_m) - _arr(extra_loss_db)

    def snr_dbhz(self, el_deg: Any, extra_loss_db: Any = 0.0, height_m: float = 0.0) -> np.ndarray:
        """Carrier-to-noise density C/N0 (dB-Hz) = received power − noise density."""
        return self.received_power_dbw(el_deg, extra_loss_db, height_m) - self.noise_density_dbwhz

    def usable(self, snr_dbhz: Any) -> np.ndarray:
        """True where the satellite is strong enough to be used (C/N0 >= the cutoff)."""
        return _arr(snr_dbhz) >= self.snr_cutoff_dbhz

    def to_params(self) -> dict[str, Any]:
        """The parameters as a TOML-ready table (None values omitted)."""
        return {k: v for k, v in self.__dict__.items() if v is not None}


def _gas_scale(atmo: Atmosphere, h_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Equivalent concentration of dry air (seed) and of water vapour (own scale height).
    k_dry = np.exp(-G_MPS2 * M_AIR_KGPMOL * h_m / (R_JPMOLK * atmo.temperature_k))
    k_wv = np.exp(-h_m / atmo.water_vapour_scale_height_m)
    return k_dry, k_wv


def _layer_integral(
    el_deg: np.ndarray, h0: float, h1: float, h_rx: float, density: Any
) -> np.ndarray:
    """∫ density(h) ds along the slant path within heights h0..h1 (km·density units)."""
    lo, hi = max(h0, h_rx), h1
    if hi <= lo:
        return np.zeros_like(el_deg)
    h = lo + (hi - lo) * (_GL_X + 1.0) / 2.0  # (n,)
    r = EARTH_RADIUS_M + h
    r_rx = EARTH_RADIUS_M + h_rx
    el = np.radians(np.maximum(el_deg, 0.0))[:, None]
    # ds/dh along a straight ray from radius r_rx at elevation el, integrable at el = 0.
    dsdh = r / np.sqrt(np.maximum(r * r - (r_rx * np.cos(el)) ** 2, 1e-6))
    vals = density(h) * dsdh
    return (vals @ _GL_W) * (hi - lo) / 2.0 / 1000.0


@functools.lru_cache(maxsize=64)
def _attenuation_table(atmo: Atmosphere, height_m: float) -> dict[str, np.ndarray]:
    el = _TABLE_EL_DEG
    gamma_o = oxygen_specific_db_per_km(F_L1_GHZ, atmo.pressure_hpa, atmo.temperature_k)
    gamma_w = water_vapour_specific_db_per_km(
        F_L1_GHZ, atmo.pressure_hpa, atmo.temperature_k, atmo.water_vapour_gm3
    )
    out: dict[str, np.ndarray] = {}
    oxygen = np.zeros_like(el)
    vapour = np.zeros_like(el)
    for name, h0, h1 in LAYERS:
        o = gamma_o * _layer_integral(el, h0, h1, height_m, lambda h: _gas_scale(atmo, h)[0])
        w = gamma_w * _layer_integral(el, h0, h1, height_m, lambda h: _gas_scale(atmo, h)[1])
        out[f"oxygen:{name}"] = o
        out[f"water_vapour:{name}"] = w
        oxygen += o
        vapour += w
    out["oxygen"] = oxygen
    out["water_vapour"] = vapour
    base, top = atmo.cloud_layer_m()
    lwc = atmo.cloud_lwc()
    out["cloud"] = (
        cloud_specific_coefficient(F_L1_GHZ) * lwc * slant_path_m(el, base, top, height_m) / 1e3
    )
    if atmo.rain_mmph > 0.0:
        k, alpha = rain_coefficients(F_L1_GHZ)
        out["rain"] = (
            k * atmo.rain_mmph**alpha * slant_path_m(el, 0.0, atmo.rain_height_m, height_m) / 1e3
        )
    else:
        out["rain"] = np.zeros_like(el)
    out["total"] = oxygen + vapour + out["cloud"] + out["rain"]
    return out
