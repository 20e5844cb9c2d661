"""Weather models of the sensor renderer: one documented set of parameters per weather.

The renderer is a small physically *motivated* (not physically calibrated) model. Radiance is in
relative linear units (``1``): a surface of albedo ``rho`` lit by the sun at normal incidence with
``sun_irradiance_rgb = 1`` and no ambient light has linear value ``rho`` before exposure. Images are
then scaled by ``exposure``, clipped to [0, 1] and sRGB-encoded to 8 bits (one fixed exposure for
every weather, so brightness differences between weathers are real differences of the scene light,
not of an auto-exposure).

Per pixel that hits a surface (Lambert shading, flat face normals):

    L = albedo * (ambient_rgb
                  + sun_irradiance_rgb * max(0, n . s) * unshadowed          (sun, with ray-cast shadows)
                  + lamp_intensity_rgb * cone(theta) * max(0, -n . d) / r**2   (lamp at the camera)
                  + sum_k street_lamp_intensity_rgb * max(0, n . l_k) / max(r_k, 1 m)**2 * unshadowed_k)
                  + aircraft_light_radiance_rgb   (faces of uav actors only: their lights)
    L = L * exp(-r / visibility_m) + haze_rgb * (1 - exp(-r / visibility_m))   (distance haze)

with ``s`` the unit vector towards the sun (``sun_azimuth_deg`` clockwise from north,
``sun_elevation_deg`` above the horizon), ``d`` the unit ray direction, ``r`` the distance from
the camera along the ray (m), ``theta`` the angle between the ray and the optical axis, and
``cone`` 1 inside ``lamp_cone_half_angle_deg``, falling linearly (in cos theta) to 0 over
``lamp_cone_falloff_deg`` more; ``l_k`` the unit vector and ``r_k`` the distance to street lamp
``k`` of the four lattice cells around the surface point (cells without road have no lamp). Pixels that hit nothing show the sky: a vertical gradient from
``sky_horizon_rgb`` (horizontal rays and below) to ``sky_zenith_rgb`` (straight up).

After tone mapping: rain streaks (``rain_streaks_per_mpx`` per megapixel, each ``rain_streak_length
_frac`` of the image height long, slanted by ``rain_streak_slant_deg``, blended with opacity
``rain_streak_alpha`` towards ``rain_streak_rgb``) are drawn into ``rgb`` only (depth and labels
are of the scene, not of the rain), then Gaussian pixel noise of ``pixel_noise_std_dn`` digital
numbers (8-bit levels) is added and the result rounded and clipped to 0..255.

LiDAR: each return is dropped with probability ``lidar_dropout_probability`` (rain absorbs and
scatters the pulse), and the configured ``range_noise_std_m`` is multiplied by
``lidar_range_noise_factor``. Neither depends on range in this first version.

IMU and GPS do not depend on the weather; their groups still carry the weather's parameters and
their noise draws are seeded with the weather's name, like every stream's.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class WeatherModel:
    """Parameters of one weather; units in the names (``_deg``, ``_m``, ``_dn``, ``_px``) else ``1``."""

    name: str
    description: str
    # Sun (a directional light). Zero irradiance switches the sun and its shadow rays off.
    sun_azimuth_deg: float          # clockwise from north (compass bearing of the sun)
    sun_elevation_deg: float        # above the horizon
    sun_irradiance_rgb: RGB         # relative linear irradiance at normal incidence
    ambient_rgb: RGB                # uniform ambient (sky) irradiance, no occlusion
    sky_zenith_rgb: RGB             # linear radiance of the sky straight up
    sky_horizon_rgb: RGB            # linear radiance of the sky at and below the horizon
    # Distance haze: blend towards haze_rgb with weight 1 - exp(-distance / visibility_m).
    haze_rgb: RGB
    visibility_m: float
    # Lamp / headlight at the camera, pointing along the optical axis (inverse-square falloff).
    lamp_intensity_rgb: RGB         # relative linear intensity (irradiance at 1 m on axis)
    lamp_cone_half_angle_deg: float
    lamp_cone_falloff_deg: float
    # Street lamps (point lights over the roads; see ``sensing.camera.street_lamps``): one lamp per
    # square lattice cell of side street_lamp_spacing_m that holds road, above the road point nearest
    # the cell centre; a pixel is lit by the four lamps of the cells around it, with ray-cast shadows.
    street_lamp_spacing_m: float    # 0 switches street lamps off
    street_lamp_height_m: float     # above the road surface
    street_lamp_intensity_rgb: RGB  # relative linear intensity (irradiance at 1 m, isotropic)
    # Camera exposure and sensor noise.
    exposure: float                 # linear scale before clipping and sRGB encoding
    pixel_noise_std_dn: float       # Gaussian noise, 8-bit digital numbers
    # Rain streaks (image-space overlay).
    rain_streaks_per_mpx: float
    rain_streak_length_frac: float  # of the image height
    rain_streak_slant_deg: float    # from vertical, positive leaning right at the bottom
    rain_streak_alpha: float
    rain_streak_rgb: RGB            # linear
    # LiDAR.
    lidar_dropout_probability: float
    lidar_range_noise_factor: float
    # Lights carried by aircraft actors (class uav): a relative linear radiance added to their faces,
    # before haze. Night flight requires lit aircraft (anti-collision lights visible for 3 statute
    # miles under 14 CFR 107.29; navigation lights in EASA's rules), so a UAV at night is a lit spot.
    aircraft_light_radiance_rgb: RGB = (0.0, 0.0, 0.0)

    def sun_direction_enu(self) -> np.ndarray:
        """Unit vector from a surface towards the sun in the ENU world frame."""
        az, el = np.deg2rad(self.sun_azimuth_deg), np.deg2rad(self.sun_elevation_deg)
        return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])

    @property
    def has_sun(self) -> bool:
        return max(self.sun_irradiance_rgb) > 0

    @property
    def has_lamp(self) -> bool:
        return max(self.lamp_intensity_rgb) > 0

    @property
    def has_street_lamps(self) -> bool:
        return self.street_lamp_spacing_m > 0 and max(self.street_lamp_intensity_rgb) > 0

    def attrs(self) -> dict:
        """Flat ``weather_<parameter>`` attrs (JSON types) for a store group."""
        out = {}
        for k, v in asdict(self).items():
            key = "weather" if k == "name" else f"weather_{k}"
            out[key] = list(v) if isinstance(v, tuple) else v
        return out


SUNNY = WeatherModel(
    name="sunny",
    description="clear sky, bright sun from the south-east at 45 deg with hard ray-cast shadows",
    sun_azimuth_deg=135.0, sun_elevation_deg=45.0,
    sun_irradiance_rgb=(1.9, 1.8, 1.6), ambient_rgb=(0.30, 0.33, 0.40),
    sky_zenith_rgb=(0.20, 0.40, 0.90), sky_horizon_rgb=(0.60, 0.75, 0.95),
    haze_rgb=(0.60, 0.70, 0.85), visibility_m=20000.0,
    lamp_intensity_rgb=(0.0, 0.0, 0.0), lamp_cone_half_angle_deg=30.0, lamp_cone_falloff_deg=15.0,
    street_lamp_spacing_m=0.0, street_lamp_height_m=6.0, street_lamp_intensity_rgb=(0.0, 0.0, 0.0),
    exposure=1.0, pixel_noise_std_dn=1.0,
    rain_streaks_per_mpx=0.0, rain_streak_length_frac=0.08, rain_streak_slant_deg=12.0,
    rain_streak_alpha=0.0, rain_streak_rgb=(0.8, 0.8, 0.85),
    lidar_dropout_probability=0.0, lidar_range_noise_factor=1.0,
)

RAINY = WeatherModel(
    name="rainy",
    description="overcast rain: weak diffuse sun, grey sky, distance haze (150 m), rain streaks, "
                "LiDAR drop-outs and noisier ranges",
    sun_azimuth_deg=135.0, sun_elevation_deg=45.0,
    sun_irradiance_rgb=(0.35, 0.35, 0.37), ambient_rgb=(0.22, 0.23, 0.25),
    sky_zenith_rgb=(0.30, 0.31, 0.33), sky_horizon_rgb=(0.38, 0.39, 0.41),
    haze_rgb=(0.36, 0.37, 0.39), visibility_m=150.0,
    lamp_intensity_rgb=(0.0, 0.0, 0.0), lamp_cone_half_angle_deg=30.0, lamp_cone_falloff_deg=15.0,
    street_lamp_spacing_m=0.0, street_lamp_height_m=6.0, street_lamp_intensity_rgb=(0.0, 0.0, 0.0),
    exposure=1.0, pixel_noise_std_dn=2.5,
    rain_streaks_per_mpx=400.0, rain_streak_length_frac=0.08, rain_streak_slant_deg=12.0,
    rain_streak_alpha=0.35, rain_streak_rgb=(0.75, 0.76, 0.80),
    lidar_dropout_probability=0.15, lidar_range_noise_factor=3.0,
)

NIGHT = WeatherModel(
    name="night",
    description="night: no sun, faint ambient, warm street lamps every 30 m over the roads (with "
                "shadows), a lamp cone from the camera (headlight), lit aircraft, strong pixel noise",
    sun_azimuth_deg=135.0, sun_elevation_deg=-30.0,
    sun_irradiance_rgb=(0.0, 0.0, 0.0), ambient_rgb=(0.012, 0.014, 0.022),
    sky_zenith_rgb=(0.002, 0.003, 0.008), sky_horizon_rgb=(0.010, 0.010, 0.016),
    haze_rgb=(0.010, 0.010, 0.014), visibility_m=3000.0,
    lamp_intensity_rgb=(60.0, 55.0, 45.0), lamp_cone_half_angle_deg=25.0, lamp_cone_falloff_deg=15.0,
    street_lamp_spacing_m=30.0, street_lamp_height_m=6.0, street_lamp_intensity_rgb=(14.0, 10.0, 5.0),
    exposure=1.0, pixel_noise_std_dn=6.0,
    rain_streaks_per_mpx=0.0, rain_streak_length_frac=0.08, rain_streak_slant_deg=12.0,
    rain_streak_alpha=0.0, rain_streak_rgb=(0.8, 0.8, 0.85),
    lidar_dropout_probability=0.0, lidar_range_noise_factor=1.0,
    aircraft_light_radiance_rgb=(0.35, 0.30, 0.30),
)

WEATHER_MODELS: dict[str, WeatherModel] = {w.name: w for w in (SUNNY, RAINY, NIGHT)}


def weather_model(name: str) -> WeatherModel:
    try:
        return WEATHER_MODELS[name]
    except KeyError:
        raise ValueError(f"unknown weather {name!r}; known: {', '.join(WEATHER_MODELS)}") from None
