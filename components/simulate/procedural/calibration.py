"""The procedural renderer's calibration table: every free constant, with its unit and meaning.

The renderer (:mod:`components.simulate.procedural.renderer` and its helpers) reads numbers only from
:data:`CALIBRATION`. Constants marked "unverified" (docs/simulators.md) are free parameters; if CARLA
images become available they are the knobs to fit. :func:`calibration_hash` fingerprints the table
and enters the renderer's ``version`` string, so datasets record which calibration made them.

Units: ``m`` metres, ``m^-1`` per metre, ``deg`` degrees, ``px@128`` pixels at 128-pixel image
height (scaled with the resolution), ``rel`` relative radiance units (clear-noon sun = ``sun_irradiance``),
``EV`` exposure value (EV100), ``1`` dimensionless.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, fields

__all__ = ["Calibration", "CALIBRATION", "calibration_rows", "calibration_hash"]


def _c(value: object, unit: str, meaning: str) -> object:
    return field(default=value, metadata={"unit": unit, "meaning": meaning})


@dataclass(frozen=True)
class Calibration:
    """All constants of the procedural renderer (frozen; one instance :data:`CALIBRATION`)."""

    # --- sun and sky (docs/simulators.md) ----------------------------------------------------------
    sun_irradiance: float = _c(3.2, "rel", "E0: direct normal sun irradiance above the atmosphere")
    rayleigh_tau: float = _c(0.0088, "1", "Rayleigh optical depth coefficient, T_c = exp(-k λ^-4.05 m)")
    wavelengths_um: tuple = _c((0.68, 0.55, 0.44), "µm", "wavelengths of the R, G, B channels")
    aerosol_tau: float = _c(0.15, "1", "aerosol (Mie) optical depth τ_a at zenith (CARLA Mie 0.03 is hazy)")
    sky_irradiance: float = _c(0.55, "rel", "clear-sky zenith radiance scale at noon (times sin(h)^sky_exponent)")
    sky_exponent: float = _c(0.7, "1", "exponent of sin(h) in the clear-sky brightness")
    twilight_level: float = _c(0.06, "1", "sky brightness at h=0 relative to the day term's scale")
    twilight_scale_deg: float = _c(1.6, "deg", "e-folding of sky brightness below the horizon (civil twilight)")
    night_sky: float = _c(1.5e-3, "rel", "night sky radiance floor (moon + city glow)")
    zenith_colour: tuple = _c((0.30, 0.52, 1.0), "1", "clear-sky zenith colour (unnormalized RGB)")
    horizon_colour: tuple = _c((0.80, 0.88, 1.0), "1", "clear-sky horizon colour at high sun")
    night_colour: tuple = _c((0.45, 0.50, 0.75), "1", "night sky colour")
    horizon_power: float = _c(3.0, "1", "horizon brightening exponent: w = (1 - sin e)^p")
    horizon_gain: float = _c(1.6, "1", "horizon radiance relative to zenith")
    low_sun_tint_deg: float = _c(10.0, "deg", "sun altitude below which the horizon takes the sun's colour")
    mie_g: float = _c(0.80, "1", "Henyey-Greenstein asymmetry of the aerosol halo around the sun")
    mie_halo: float = _c(0.035, "1", "aerosol halo radiance per unit direct sun irradiance")
    glare_g: float = _c(0.97, "1", "HG asymmetry of the narrow sun glare lobe")
    glare: float = _c(0.012, "1", "narrow sun glare radiance per unit direct sun irradiance")
    sun_edge_deg: float = _c(0.6, "deg", "half width of the sunrise/sunset ramp of the direct sun")
    # --- clouds (§2.3) ------------------------------------------------------------------------------
    cloud_height: float = _c(2000.0, "m", "altitude H_c of the 2-D cloud plane")
    cloud_scale: float = _c(2500.0, "m", "horizontal size of one period of the cloud noise texture")
    cloud_edge: float = _c(0.18, "1", "soft coverage edge width w of α = clip((n-1+C(1+w))/w)")
    cloud_sun: float = _c(0.22, "1", "cloud radiance per unit direct sun irradiance (lit tops, thin cloud)")
    cloud_ambient: float = _c(1.25, "1", "cloud radiance per unit sky radiance")
    cloud_silver: float = _c(0.6, "1", "forward-scattering silver lining weight near the sun")
    cloud_silver_g: float = _c(0.6, "1", "HG asymmetry of the silver lining")
    cloud_thickening: float = _c(0.55, "1", "darkening of the cloud base as coverage → 100 %")
    cloud_dimming: float = _c(0.92, "1", "fraction of direct sun removed at 100 % cloudiness")
    cloud_dimming_exponent: float = _c(1.6, "1", "p in E_sun × (1 - k C^p)")
    overcast_diffuse: float = _c(0.35, "1", "fraction of the removed direct sun returned as diffuse light")
    cloud_night_glow: float = _c(1.15, "1", "cloud radiance / sky radiance at night (city glow; nearly invisible)")
    cloud_sky_loss: float = _c(0.5, "1", "fraction of clear-sky diffuse light lost at 100 % cloudiness")
    # --- fog and rain extinction (§2.1) -----------------------------------------------------------
    fog_extinction: float = _c(0.07, "m^-1", "κ: fog extinction β_fog at fog_density 100 % (MOR 43 m)")
    base_extinction: float = _c(0.0012, "m^-1", "aerosol haze always present (CARLA Mie 0.03)")
    fog_scale_height: float = _c(144.0, "m", "e-folding height of the height fog (falloff 0.1); sky integral")
    sky_max_path: float = _c(4000.0, "m", "cap of the horizontal optical path of sky rays")
    fog_sun_dimming: float = _c(0.7, "1", "k_f: E_sun × (1 - k_f fog/100)")
    airlight_ambient: float = _c(0.9, "1", "airlight radiance per unit ambient radiance")
    airlight_sun: float = _c(0.10, "1", "airlight HG sun lobe per unit direct sun irradiance")
    airlight_g: float = _c(0.75, "1", "HG asymmetry of the fog sun lobe")
    rain_rate_max: float = _c(100.0, "mm/h", "R_max: rain rate at precipitation 100 %")
    rain_rate_exponent: float = _c(1.5, "1", "γ in R = R_max (p/100)^γ")
    rain_extinction: float = _c(0.312e-3, "m^-1", "β_rain = k R^0.67 (Weber 2015), per (mm/h)^0.67")
    # --- rain streaks and lens drops (§2.4) -------------------------------------------------------
    rain_drop_pool: int = _c(700, "1", "pre-drawn rain drops per scene (the same at every image size)")
    rain_count_exponent: float = _c(0.7, "1", "fraction of pool drawn = (R/R_max)^exponent")
    rain_near: float = _c(0.8, "m", "nearest drawn drop depth")
    rain_far: float = _c(8.0, "m", "farthest drawn drop depth (farther rain enters as β_rain)")
    streak_exposure: float = _c(0.08, "s", "effective exposure for streak length (artist-tuned, CARLA-like)")
    streak_max_px: float = _c(26.0, "px@128", "cap of streak length")
    streak_alpha: float = _c(0.55, "1", "peak opacity of a streak at 100 % precipitation")
    streak_alpha_exponent: float = _c(0.5, "1", "opacity ∝ (p/100)^exponent")
    streak_near_depth: float = _c(3.0, "m", "depth nearer than which a streak has full opacity (∝ 1/Z beyond)")
    streak_far_alpha: float = _c(0.25, "1", "opacity floor (relative) of the farthest streaks")
    streak_alpha_cap: float = _c(0.9, "1", "maximum accumulated streak opacity of a pixel")
    streak_brightness: float = _c(2.2, "1", "streak radiance / mean scene radiance (+ airlight)")
    wind_speed_max: float = _c(9.0, "m/s", "k_w: horizontal wind speed at wind_intensity 100 %")
    lens_drop_pool: int = _c(28, "1", "pre-drawn lens drops per scene")
    lens_drop_radius: tuple = _c((0.02, 0.06), "1", "lens drop radius range, fraction of image width")
    lens_drop_fraction: float = _c(0.8, "1", "fraction of the lens-drop pool active at 100 % precipitation")
    lens_drop_magnification: float = _c(-0.55, "1", "refraction: drop samples centre + m·offset (negative = flipped)")
    lens_blur_px: float = _c(3.0, "px@128", "blur of the scene seen through a lens drop")
    # --- puddles (§2.5) ----------------------------------------------------------------------------
    puddle_scale: float = _c(9.0, "m", "world size of one puddle-noise period")
    puddle_edge: float = _c(0.08, "1", "soft puddle edge width in noise quantile")
    water_f0: float = _c(0.02, "1", "Schlick F0 of water (n = 1.33)")
    puddle_darkening: float = _c(0.45, "1", "diffuse factor of the flooded road under the water")
    puddle_min_reflectance: float = _c(0.12, "1", "reflectance floor (calm water seen from a car is mirror-like)")
    ripple_saturation: float = _c(30.0, "%", "precipitation at which puddle ripples are fully developed")
    ripple_px: float = _c(1.5, "px@128", "screen-space jitter of the reflection by ripples")
    # --- surfaces and shadows (§2.6) ---------------------------------------------------------------
    ambient_vertical: float = _c(0.55, "1", "ambient (sky-view) factor of vertical surfaces")
    shadow_map_cell: float = _c(0.25, "m", "cell size of the ground shadow raster")
    shadow_map_extent: tuple = _c((-30.0, 30.0, -5.0, 160.0), "m", "ground shadow raster x0, x1, z0, z1")
    texture_seed: int = _c(20261121, "1", "seed of the static world noise textures (surfaces, clouds, puddles)")
    texture_strength: float = _c(0.25, "1", "relative albedo variation of surface textures")
    # --- night lighting (§2.7) ---------------------------------------------------------------------
    lamp_intensity: float = _c(60.0, "rel·m²", "street lamp intensity I (E = I cos/r²)")
    lamp_colour: tuple = _c((1.0, 0.78, 0.52), "1", "street lamp colour (sodium/LED mix)")
    lamp_core: float = _c(10.0, "rel", "lamp head emitted radiance (glow sprite peak)")
    lamp_halo: float = _c(0.3, "rel", "lamp halo radiance at full fog (HG halo)")
    lamp_halo_px: float = _c(3.5, "px@128", "σ of the lamp halo sprite")
    lamp_halo_path: float = _c(40.0, "m", "fog path whose scattering makes the lamp halo: halo ∝ 1 − exp(−β·path)")
    lamp_halo_haze: float = _c(0.04, "1", "halo weight without fog (aerosol Mie halo)")
    lamp_reference_distance: float = _c(15.0, "m", "distance below which a lamp sprite keeps its full radiance")
    light_reference_distance: float = _c(10.0, "m", "same for vehicle lights")
    sprite_px: float = _c(0.7, "px@128", "σ of lamp/vehicle-light core sprites")
    headlight_cone_exponent: float = _c(10.0, "1", "head-light beam: intensity ∝ cos^k of the off-axis angle")
    headlight_intensity: float = _c(30.0, "rel·m²", "vehicle headlight intensity on the road")
    headlight_core: float = _c(25.0, "rel", "head-light sprite radiance")
    taillight_core: float = _c(6.0, "rel", "tail-light sprite radiance")
    window_emission: float = _c(0.25, "rel", "radiance of a lit window at night")
    window_lit_fraction: float = _c(0.45, "1", "fraction of windows lit at night")
    # --- camera (§2.8) -----------------------------------------------------------------------------
    radiance_to_luminance: float = _c(1500.0, "cd/m² per rel", "scale from relative radiance to luminance")
    exposure_window: tuple = _c((10.0, 12.0), "EV", "auto-exposure limits (CARLA min/max bright)")
    exposure_compensation: float = _c(1.4, "EV", "exposure bias before the filmic curve")
    luminance_clip: float = _c(4.0, "rel", "radiance clip in the metering average (sun/lamps excluded)")
    gamma: float = _c(2.2, "1", "display gamma")
    # --- scene nuisance (§5 layout) ----------------------------------------------------------------
    archetypes: tuple = _c(("urban_canyon", "suburban", "highway", "rural"), "-", "scene archetypes (maps)")
    archetype_weights: tuple = _c((0.3, 0.3, 0.2, 0.2), "1", "probability of each archetype")
    ego_extent_z: tuple = _c((0.62, 0.70, 0.75, 0.96, 1.05, 1.30, 1.55), "m", "ego bounding-box half heights")
    fov_deg: tuple = _c((80.0, 100.0), "deg", "horizontal field of view range")
    pitch_deg: float = _c(2.0, "deg", "camera pitch ±")
    yaw_deg: float = _c(4.0, "deg", "camera yaw relative to the road ±")
    lane_width: float = _c(3.5, "m", "lane width")
    scene_length: float = _c(240.0, "m", "length of the built road ahead")
    lamp_spacing: tuple = _c((25.0, 40.0), "m", "street lamp spacing range")
    lamp_height: tuple = _c((6.0, 9.0), "m", "street lamp height range")
    vehicles_mean: tuple = _c((6.0, 4.0, 9.0, 2.0), "1", "Poisson mean of moving vehicles per archetype")
    pedestrians_mean: tuple = _c((7.0, 3.0, 0.0, 0.5), "1", "Poisson mean of pedestrians per archetype")
    vehicle_range: tuple = _c((6.0, 90.0), "m", "distance range of traffic ahead")


CALIBRATION = Calibration()


def calibration_rows(cal: Calibration = CALIBRATION) -> list[tuple[str, object, str, str]]:
    """The table as ``(name, value, unit, meaning)`` rows, in declaration order."""
    return [(f.name, getattr(cal, f.name), f.metadata["unit"], f.metadata["meaning"]) for f in fields(cal)]


def calibration_hash(cal: Calibration = CALIBRATION) -> str:
    """An 8-hex-digit fingerprint of the table's names and values."""
    text = ";".join(f"{n}={v!r}" for n, v, _, _ in calibration_rows(cal))
    return hashlib.sha1(text.encode("utf-8")).hexdigest()[:8]
