"""Radio materials: the ITU-R P.2040 set, water, and rain-wetted facades, at the carrier frequency.

One place for every radio material the project writes into a Sionna RT scene or swaps in for a
weather. ITU materials are Sionna RT's own ``itu-radio-material`` (ITU-R P.2040-3 Table 3, which
Sionna evaluates at the scene frequency). The others are ``radio-material`` BSDFs whose relative
permittivity and conductivity this module computes at the carrier frequency:

- ``sea_water`` / ``fresh_water``: the single-Debye model of Klein & Swift (1977), "An improved
  model for the dielectric constant of sea water at microwave frequencies", IEEE Trans. Antennas
  Propag. 25(1), 104-111, at 20 degC and salinity 35 psu (sea) or 0 psu (fresh). Valid 1-10 GHz
  or so; above it the double-Debye model of ITU-R P.527-6 is the better reference.
- ``wet_concrete`` / ``wet_brick``: a rain-soaked facade. The dry material (ITU-R P.2040-3 Table 3)
  takes up fresh water in its pores, mixed by the complex refractive index model (CRIM; Birchak et
  al. 1974, Proc. IEEE 62(1), 93-98): ``sqrt(eps_wet) = sqrt(eps_dry) + theta (sqrt(eps_water) - 1)``
  where ``theta`` is the volumetric water content that replaces air in the pores
  (:data:`WET_FACADE_WATER_CONTENT`; 0.10 for a surface layer near saturation: concrete porosity
  is 10-15 %, fired brick 15-30 %).

Conductivity follows from the imaginary part: ``sigma = eps'' eps_0 omega`` (time convention
``exp(+j omega t)``, ``eps = eps' - j eps''``), as in ITU-R P.2040.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from scipy.constants import epsilon_0

from simart_pipeline.vocabulary import ITU_MATERIALS, RADIO_MATERIALS, WEATHER_MATERIALS  # noqa: F401 (re-exported)


# ITU-R P.2040-3 Table 3: eps' = a f^b, sigma = c f^d (f in GHz), for the dry bases of wet facades.
ITU_P2040_TABLE3 = {
    "concrete": (5.24, 0.0, 0.0462, 0.7822),
    "brick": (3.91, 0.0, 0.0238, 0.16),
}
WET_FACADE_WATER_CONTENT = {"wet_concrete": 0.10, "wet_brick": 0.10}
WATER_TEMPERATURE_C = 20.0
SEA_SALINITY_PSU = 35.0


@dataclass(frozen=True)
class CustomMaterial:
    name: str
    description: str
    source: str


CUSTOM_MATERIALS: dict[str, CustomMaterial] = {m.name: m for m in (
    CustomMaterial("sea_water", f"sea water, {SEA_SALINITY_PSU:g} psu, {WATER_TEMPERATURE_C:g} degC",
                   "Klein & Swift 1977, IEEE TAP 25(1):104-111 (single Debye)"),
    CustomMaterial("fresh_water", f"fresh water, {WATER_TEMPERATURE_C:g} degC",
                   "Klein & Swift 1977, IEEE TAP 25(1):104-111 (single Debye, salinity 0)"),
    CustomMaterial("wet_concrete", "rain-soaked concrete facade (10 % water by volume)",
                   "ITU-R P.2040-3 Table 3 concrete + fresh water, CRIM mixing (Birchak et al. 1974)"),
    CustomMaterial("wet_brick", "rain-soaked brick facade (10 % water by volume)",
                   "ITU-R P.2040-3 Table 3 brick + fresh water, CRIM mixing (Birchak et al. 1974)"),
)}


def weathers_sharing_materials(weathers) -> dict[str, list[str]]:
    """The one reuse policy of radio work across weathers, for the CIRs and the channel knowledge
    maps alike: weathers whose rows of :data:`WEATHER_MATERIALS` are equal use the same set of radio
    materials, so they share one trace and one map, named after the first weather of the set
    (:data:`WEATHER_GROUP`: sunny and night use the dry set ``sunny``; rain the wet set ``rainy``,
    whose swaps a scene sets in ``materials.rain``)."""
    groups: dict[str, list[str]] = {}
    for w in weathers:
        if w not in WEATHER_GROUP:
            raise ValueError(f"unknown weather {w!r}; known: {', '.join(WEATHER_GROUP)}")
        groups.setdefault(WEATHER_GROUP[w], []).append(w)
    return groups


# Weather -> the weather group whose radio materials it uses (the first weather with an equal row).
WEATHER_GROUP: dict[str, str] = {
    w: next(g for g in WEATHER_MATERIALS if WEATHER_MATERIALS[g] == WEATHER_MATERIALS[w]) for w in WEATHER_MATERIALS}
WEATHER_GROUPS: tuple[str, ...] = tuple(dict.fromkeys(WEATHER_GROUP.values()))


def water_permittivity(frequency_hz: float, temperature_c: float = WATER_TEMPERATURE_C,
                       salinity_psu: float = 0.0) -> complex:
    """Complex relative permittivity ``eps' - j eps''`` of water (Klein & Swift 1977)."""
    t, s = temperature_c, salinity_psu
    eps_static_pure = 87.134 - 1.949e-1 * t - 1.276e-2 * t**2 + 2.491e-4 * t**3
    a = 1.0 + 1.613e-5 * t * s - 3.656e-3 * s + 3.210e-5 * s**2 - 4.232e-7 * s**3
    tau_pure_s = 1.768e-11 - 6.086e-13 * t + 1.104e-14 * t**2 - 8.111e-17 * t**3
    b = 1.0 + 2.282e-5 * t * s - 7.638e-4 * s - 7.760e-6 * s**2 + 1.105e-8 * s**3
    eps_inf = 4.9
    sigma = 0.0
    if s > 0:
        d = 25.0 - t
        sigma_25 = s * (0.182521 - 1.46192e-3 * s + 2.09324e-5 * s**2 - 1.28205e-7 * s**3)
        phi = d * (2.033e-2 + 1.266e-4 * d + 2.464e-6 * d**2
                   - s * (1.849e-5 - 2.551e-7 * d + 2.551e-8 * d**2))
        sigma = sigma_25 * math.exp(-phi)
    omega = 2 * math.pi * frequency_hz
    debye = eps_inf + (eps_static_pure * a - eps_inf) / (1 + 1j * omega * tau_pure_s * b)
    return complex(debye - 1j * sigma / (omega * epsilon_0))


def itu_permittivity(name: str, frequency_hz: float) -> complex:
    """ITU-R P.2040-3 Table 3 complex relative permittivity of a dry base material."""
    a, b, c, d = ITU_P2040_TABLE3[name]
    f_ghz = frequency_hz / 1e9
    sigma = c * f_ghz**d
    return complex(a * f_ghz**b, -sigma / (2 * math.pi * frequency_hz * epsilon_0))


def permittivity(name: str, frequency_hz: float) -> complex:
    """Complex relative permittivity of a custom material at ``frequency_hz``."""
    if name == "sea_water":
        return water_permittivity(frequency_hz, salinity_psu=SEA_SALINITY_PSU)
    if name == "fresh_water":
        return water_permittivity(frequency_hz)
    if name in WET_FACADE_WATER_CONTENT:
        theta = WET_FACADE_WATER_CONTENT[name]
        dry = itu_permittivity(name.removeprefix("wet_"), frequency_hz)
        root = dry**0.5 + theta * (water_permittivity(frequency_hz) ** 0.5 - 1.0)
        return complex(root**2)
    raise ValueError(f"{name!r} is not a custom radio material; known: {', '.join(CUSTOM_MATERIALS)}")


def permittivity_conductivity(name: str, frequency_hz: float) -> tuple[float, float]:
    """(relative permittivity eps', conductivity in S/m) of a custom material."""
    eps = permittivity(name, frequency_hz)
    return eps.real, -eps.imag * epsilon_0 * 2 * math.pi * frequency_hz


def check_known(name: str) -> str:
    if name not in RADIO_MATERIALS:
        raise ValueError(f"unknown radio material {name!r}; known: {', '.join(RADIO_MATERIALS)}")
    return name


def bsdf_id(name: str) -> str:
    return f"mat_{check_known(name)}"


def bsdf_xml(name: str, frequency_hz: float, thickness_m: float) -> str:
    """One Mitsuba ``<bsdf>`` element that Sionna RT's ``load_scene`` reads as radio material ``name``."""
    ident = quoteattr(bsdf_id(name))
    if name in ITU_MATERIALS:
        return (f'<bsdf type="itu-radio-material" id={ident}>'
                f'<string name="type" value={quoteattr(name)}/>'
                f'<float name="thickness" value="{thickness_m!r}"/></bsdf>')
    eps_r, sigma = permittivity_conductivity(name, frequency_hz)
    return (f'<!-- {CUSTOM_MATERIALS[name].description}; at {frequency_hz:g} Hz; '
            f'{CUSTOM_MATERIALS[name].source} -->'
            f'<bsdf type="radio-material" id={ident}>'
            f'<float name="relative_permittivity" value="{eps_r!r}"/>'
            f'<float name="conductivity" value="{sigma!r}"/>'
            f'<float name="thickness" value="{thickness_m!r}"/></bsdf>')


def sionna_material(name: str, frequency_hz: float, thickness_m: float, suffix: str = ""):
    """A Sionna RT radio material object for ``name`` (for swapping materials on a loaded scene)."""
    import sionna.rt as rt

    check_known(name)
    if name in ITU_MATERIALS:
        return rt.ITURadioMaterial(f"{bsdf_id(name)}{suffix}", name, thickness=thickness_m)
    eps_r, sigma = permittivity_conductivity(name, frequency_hz)
    return rt.RadioMaterial(f"{bsdf_id(name)}{suffix}", relative_permittivity=eps_r,
                            conductivity=sigma, thickness=thickness_m)


def material_name(radio_material) -> str:
    """The project's name of a Sionna radio material object (inverse of bsdf_id / sionna_material)."""
    itu = getattr(radio_material, "itu_type", None)
    if itu:
        return itu
    name = radio_material.name
    for known in sorted(RADIO_MATERIALS, key=len, reverse=True):
        if name == f"mat_{known}" or name.startswith(f"mat_{known}_"):
            return known
    return name
