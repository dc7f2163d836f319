"""Sun, sky and cloud radiance from the sun altitude, relative azimuth and cloudiness (§2.2–2.3).

Notation: h sun altitude (deg), φ sun azimuth relative to the camera heading (deg), s the unit
vector towards the sun, C = cloudiness/100. Radiance is linear RGB in the relative units of
:mod:`components.simulate.procedural.calibration`. The sun's colour is Rayleigh + aerosol transmittance along
the Kasten–Young air mass; the sky is a zenith/horizon two-colour gradient keyed by h with a
Henyey–Greenstein aerosol halo and glare around the sun; below the horizon it fades through a civil
twilight band to a night floor. Clouds are a 2-D layer whose coverage α comes from a static noise
quantile field thresholded by C (so coverage follows cloudiness, and the same clouds persist).

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .calibration import CALIBRATION, Calibration

__all__ = ["SunSky", "sun_sky", "henyey_greenstein", "sky_radiance", "cloud_coverage"]


def henyey_greenstein(cos_gamma: np.ndarray | float, g: float) -> np.ndarray:
    """HG phase function (1/sr) at scattering-angle cosine ``cos_gamma``."""
    x = np.float32(1 + g * g) - np.float32(2 * g) * np.asarray(cos_gamma, dtype=np.float32)
    return np.float32((1 - g * g) / (4 * math.pi)) / (x * np.sqrt(x))


@dataclass(frozen=True)
class SunSky:
    """Illumination state for one (h, φ, C, fog): everything is a scalar or an RGB triple (3,).

    ``sun_dir`` unit vector to the sun (world frame), ``sun`` direct normal irradiance after
    clouds and fog, ``sun_clear`` before them, ``sky`` clear zenith sky radiance, ``zenith`` and
    ``horizon`` sky colours, ``ambient`` diffuse irradiance/π on a horizontal surface, ``night``
    1.0 when lamps are on (h < 0), ``day`` a 0–1 daylight weight.
    """

    sun_dir: np.ndarray
    sun: np.ndarray
    sun_clear: np.ndarray
    sky: float
    zenith: np.ndarray
    horizon: np.ndarray
    ambient: np.ndarray
    night: float
    day: float


def _transmittance(h_deg: float, cal: Calibration) -> np.ndarray:
    h = max(h_deg, -0.5)
    m = 1.0 / (math.sin(math.radians(max(h, 0.0))) + 0.50572 * (h + 6.07995) ** -1.6364)
    lam = np.asarray(cal.wavelengths_um)
    return np.exp(-(cal.rayleigh_tau * lam**-4.05 + cal.aerosol_tau) * m)


def sun_sky(
    altitude: float, rel_azimuth: float, cloudiness: float, fog: float, cal: Calibration = CALIBRATION
) -> SunSky:
    """The sun/sky state: ``altitude``, ``rel_azimuth`` in degrees, ``cloudiness``, ``fog`` in %."""
    h, phi = math.radians(altitude), math.radians(rel_azimuth)
    s = np.array([math.cos(h) * math.sin(phi), math.sin(h), math.cos(h) * math.cos(phi)])
    edge = min(max((altitude + cal.sun_edge_deg) / (2 * cal.sun_edge_deg), 0.0), 1.0)
    trans = _transmittance(altitude, cal)
    sun_clear = cal.sun_irradiance * trans * edge
    C = cloudiness / 100.0
    cloud_keep = 1.0 - cal.cloud_dimming * C**cal.cloud_dimming_exponent
    fog_keep = 1.0 - cal.fog_sun_dimming * fog / 100.0
    sun = sun_clear * cloud_keep * fog_keep
    sin_h = max(math.sin(h), 0.0)
    level = sin_h**cal.sky_exponent + cal.twilight_level * math.exp(min(altitude, 0.0) / cal.twilight_scale_deg)
    sky = cal.sky_irradiance * level + cal.night_sky
    day = min(max(level / (cal.twilight_level * 2), 0.0), 1.0)
    zen = np.asarray(cal.zenith_colour, dtype=np.float64)
    night_c = np.asarray(cal.night_colour, dtype=np.float64)
    tint = math.exp(-max(altitude, 0.0) / cal.low_sun_tint_deg)
    hor = np.asarray(cal.horizon_colour) * (1 - tint) + tint * (trans / trans.max() * 0.8 + 0.2)
    zenith = day * zen + (1 - day) * night_c
    horizon = (day * hor + (1 - day) * night_c) * cal.horizon_gain
    # diffuse light on the ground: clear sky (hemisphere average of the gradient) + light scattered by clouds
    clear_amb = sky * 0.5 * (zenith + horizon)
    returned = cal.overcast_diffuse * (sun_clear - sun_clear * cloud_keep) * sin_h / math.pi
    ambient = clear_amb * (1.0 - cal.cloud_sky_loss * C) + returned
    return SunSky(s, sun, sun_clear, float(sky), zenith, horizon, ambient, 1.0 if altitude < 0 else 0.0, float(day))


def cloud_coverage(quantile: np.ndarray, cloudiness: float, cal: Calibration = CALIBRATION) -> np.ndarray:
    """α = clip((n − 1 + C(1+w))/w, 0, 1) for noise quantiles n: 0 at C = 0, 1 everywhere at C = 1."""
    C = cloudiness / 100.0
    w = cal.cloud_edge
    return np.clip((quantile - (1.0 - C * (1.0 + w))) * (1.0 / w), 0.0, 1.0)


def sky_radiance(
    state: SunSky,
    dir_y: np.ndarray,
    cos_gamma: np.ndarray,
    alpha: np.ndarray,
    cloudiness: float,
    cal: Calibration = CALIBRATION,
) -> np.ndarray:
    """Sky radiance (3, n) float32 (channel-planar) for rays with elevation sine ``dir_y`` (n,),
    cosine ``cos_gamma`` of the angle to the sun (n,) and cloud coverage ``alpha`` (n,)."""
    e = np.clip(dir_y, 0.0, 1.0)
    one_e = 1.0 - e
    w = one_e * one_e * one_e if cal.horizon_power == 3.0 else one_e**cal.horizon_power
    zen = state.zenith.astype(np.float32)[:, None]
    hor = state.horizon.astype(np.float32)[:, None]
    sun = state.sun_clear.astype(np.float32)[:, None]
    lobe = cal.mie_halo * henyey_greenstein(cos_gamma, cal.mie_g) + cal.glare * henyey_greenstein(
        cos_gamma, cal.glare_g
    )
    clear = np.float32(state.sky) * zen + (np.float32(state.sky) * (hor - zen)) * w[None, :] + sun * lobe[None, :]
    C = cloudiness / 100.0
    if C <= 0.0:
        return clear
    grey = np.float32(state.sky * 0.5 * (float(zen.mean()) + float(hor.mean())))
    lit = np.float32(cal.cloud_sun) * (
        1.0 + np.float32(cal.cloud_silver * 0.4 * math.pi) * henyey_greenstein(cos_gamma, cal.cloud_silver_g)
    )
    thin = np.float32(1.0 - cal.cloud_thickening * C)
    cloud = thin * (cal.cloud_ambient * grey + (sun * np.float32(max(state.sun_dir[1], 0.05) ** 0.5)) * lit[None, :])
    if state.night > 0:
        base = np.float32(state.sky) * zen + (np.float32(state.sky) * (hor - zen)) * w[None, :]
        cloud = np.maximum(cloud, np.float32(cal.cloud_night_glow) * base)
    return clear + alpha[None, :] * (cloud - clear)
