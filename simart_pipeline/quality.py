"""Data-quality checks: the rules of docs/data-contract.md, asserted on what was written.

Plain functions with no Dagster import: each takes a dataset (or a tree of datasets) and, where it
needs one, the scene config, and returns a :class:`CheckResult`: whether it passed, one line saying
what was found, numbers for metadata, and the first few problems. ``assets/checks.py`` runs them as
Dagster asset checks with every materialisation (docs/design.md, "Checks").

- :func:`finite_values`: no inf anywhere; NaN only in float variables whose attrs carry
  ``nan_means`` (the writer's rule, :func:`simart_pipeline.stores.check_finite`).
- :func:`on_shared_clock`: every stream's ``time`` is int64 ns, strictly increasing, within
  ``[0, clock.duration_s]``; streams the pipeline samples itself hold exactly
  ``clock.sample_times_ns(duration_s, rate_hz)`` of their rate.
- :func:`known_frame_ids`: every frame id named in attrs is ``world`` or a frame of the config.
- :func:`passive_channel`: no CIR path has more gain than free space at the tx-rx distance (times
  the arrays' largest element gains), and none arrives before the line of sight.
- :func:`ckm_tile`: a CKM tile is marked complete in every map; fractions of masked and empty cells.
- :func:`ckm_passive`: no CKM cell gains more than free space allows, nor arrives before the LoS.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np
import xarray as xr

from simart_pipeline import clock, frames
from simart_pipeline.sensing.contract import IMPORTED
from simart_pipeline.vocabulary import SPEED_OF_LIGHT_MPS

MAX_PROBLEMS = 5  # problems listed in a result; the count says how many there were

# Largest gain (dBi) of each Sionna RT element pattern (sionna.rt.antenna_pattern): iso 1,
# dipole 1.5, half-wave dipole 1.643, 3GPP TR 38.901 G_E,max = 8 dBi.
ELEMENT_MAX_GAIN_DBI = {"iso": 0.0, "dipole": 10 * math.log10(1.5), "hw_dipole": 10 * math.log10(1.643),
                        "tr38901": 8.0}
GAIN_TOLERANCE_DB = 0.1  # float32 path coefficients
DELAY_TOLERANCE_S = 1e-11  # plus DELAY_TOLERANCE_REL of the LoS delay (float32 delays in the solver)
DELAY_TOLERANCE_REL = 1e-6

# Attrs whose value is a frame id of this project (``source_frame_id`` and ``base_frame_id`` name
# the frames of a recording, not ours).
FRAME_ATTRS = ("frame_id", "parent_frame_id", "sensor_frame_id", "child_frame_id", "world_frame_id")
# A frame id may be per element of a dimension: "<platform>/base_link" is ``<p>/base_link`` for each
# value p of the coordinate ``platform``.
_TEMPLATE = re.compile(r"<([A-Za-z_][A-Za-z0-9_]*)>")


@dataclass
class CheckResult:
    passed: bool
    description: str
    metadata: dict = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @classmethod
    def of(cls, problems: list[str], ok: str, metadata: dict) -> "CheckResult":
        n = len(problems)
        desc = ok if not n else f"{n} problem(s): {problems[0]}" + (f" (and {n - 1} more)" if n > 1 else "")
        return cls(not n, desc, {**metadata, "problems": n}, problems[:MAX_PROBLEMS])


def _nodes(obj: xr.Dataset | xr.DataTree) -> list[tuple[str, xr.Dataset]]:
    if isinstance(obj, xr.DataTree):
        return [(node.path, node.to_dataset(inherit=False)) for node in obj.subtree]
    return [("/", obj)]


# -- finite values ----------------------------------------------------------------------------------

def finite_values(obj: xr.Dataset | xr.DataTree) -> CheckResult:
    """No inf anywhere; NaN only in float variables that declare ``nan_means``."""
    problems, n_vars, n_float, n_nan_vars, n_values = [], 0, 0, 0, 0
    for group, ds in _nodes(obj):
        for name, var in ds.variables.items():
            n_vars += 1
            if not np.issubdtype(var.dtype, np.inexact):
                continue
            n_float += 1
            values = np.asarray(var.values)
            n_values += values.size
            n_inf = int(np.isinf(values).sum())
            n_nan = int(np.isnan(values).sum())
            if n_inf:
                problems.append(f"{group}:{name} holds {n_inf} inf")
            if n_nan:
                if "nan_means" in var.attrs:
                    n_nan_vars += 1
                else:
                    problems.append(f"{group}:{name} holds {n_nan} NaN without a 'nan_means' attr")
    return CheckResult.of(problems, f"{n_float} float variables of {n_vars} finite where valid "
                          f"({n_nan_vars} with documented NaN)",
                          {"variables_checked": n_vars, "float_variables": n_float,
                           "variables_with_nan_means": n_nan_vars, "values_checked": n_values})


# -- the shared clock -------------------------------------------------------------------------------

def is_imported(ds: xr.Dataset) -> bool:
    """A stream imported from a recording (sensing/bag_import.py): its instants are the messages'
    (the stream contract's ``source`` attr, ``sensing.contract.IMPORTED``)."""
    return ds.attrs.get("source") == IMPORTED


def stream_rate_hz(group: str, ds: xr.Dataset, cfg, asset: str) -> float | None:
    """The rate whose clock instants a stream must hold exactly; None when only the general rule
    applies (an imported stream)."""
    kind = asset if asset not in ("session",) else group.strip("/").split("/")[0]
    if kind == "trajectory":
        return cfg.clock.pose_rate_hz
    if kind in ("cirs", "kpis"):
        return cfg.clock.radio_rate_hz
    if kind == "radar_frames":  # one group per radar base station
        bs = {b.name: b for b in cfg.base_stations}[group.strip("/")]
        return bs.radar.rate_hz
    if kind in ("sensor_frames", "sensors"):
        if is_imported(ds):
            return None
        if "rate_hz" not in ds.attrs:
            raise KeyError("a rendered sensor group without a 'rate_hz' attr")
        return float(ds.attrs["rate_hz"])
    raise KeyError(f"no clock rule for {asset}{group}")


def on_shared_clock(obj: xr.Dataset | xr.DataTree, cfg, asset: str) -> CheckResult:
    """Every group with data holds ``time``: int64 ns, strictly increasing, in ``[0, duration]``,
    and, where the pipeline sampled it, exactly the clock instants of its rate."""
    problems, n_streams, n_exact, n_samples = [], 0, 0, 0
    end_ns = clock.seconds_to_ns(cfg.clock.duration_s)
    worst_ns = 0
    for group, ds in _nodes(obj):
        if not ds.data_vars or group == "/" and isinstance(obj, xr.DataTree):
            continue
        where = f"{group}:time"
        n_streams += 1
        if "time" not in ds.variables:
            problems.append(f"{group}: no time coordinate")
            continue
        t = np.asarray(ds["time"].values)
        n_samples += t.size
        if t.dtype != np.int64:
            problems.append(f"{where} is {t.dtype}, not int64 ns")
            continue
        if t.size and (t[0] < 0 or t[-1] > end_ns):
            problems.append(f"{where} spans [{t.min()}, {t.max()}] ns, outside [0, {end_ns}] ns")
        if (np.diff(t) <= 0).any():
            problems.append(f"{where} is not strictly increasing")
        try:
            rate = stream_rate_hz(group, ds, cfg, asset)
        except KeyError as exc:
            problems.append(f"{group}: {exc}")
            continue
        if rate is None:
            continue
        n_exact += 1
        want = clock.sample_times_ns(cfg.clock.duration_s, rate)
        if t.shape != want.shape:
            problems.append(f"{where} holds {t.size} instants; {rate:g} Hz over {cfg.clock.duration_s:g} s "
                            f"has {want.size}")
        elif not np.array_equal(t, want):
            off = np.abs(t - want)
            worst_ns = max(worst_ns, int(off.max()))
            problems.append(f"{where} is off the {rate:g} Hz clock by up to {int(off.max())} ns "
                            f"(first at sample {int(np.argmax(off > 0))})")
    return CheckResult.of(problems, f"{n_streams} streams on the clock ({n_exact} at exact rate instants)",
                          {"streams_checked": n_streams, "streams_at_exact_instants": n_exact,
                           "samples_checked": n_samples, "worst_offset_ns": worst_ns})


# -- frame ids ---------------------------------------------------------------------------------------

def config_frames(cfg) -> set[str]:
    """``world``, every device's ``base_link``, every configured or imported sensor's frame (and a
    camera's optical frame)."""
    known = {frames.WORLD}
    sensors = []
    for dev in (*cfg.platforms, *cfg.base_stations):
        known.add(frames.base_link(dev.name))
        sensors += [(dev.name, s.name, s.kind) for s in dev.sensors]
    sensors += [(st.device, st.sensor, st.kind) for imp in cfg.sensor_imports for st in imp.streams]
    for device, sensor, kind in sensors:
        known.add(frames.sensor_frame(device, sensor))
        if kind == "camera":
            known.add(frames.sensor_frame(device, sensor, optical=True))
    return known


def _expand(frame: str, ds: xr.Dataset) -> list[str] | None:
    """A frame id with ``<dim>`` placeholders, once per value of that coordinate (None: no such
    coordinate in the dataset)."""
    names = _TEMPLATE.findall(frame)
    if not names:
        return [frame]
    out = [frame]
    for dim in names:
        if dim not in ds.coords:
            return None
        out = [f.replace(f"<{dim}>", str(v)) for f in out for v in np.asarray(ds[dim].values).ravel()]
    return out


def known_frame_ids(obj: xr.Dataset | xr.DataTree, cfg) -> CheckResult:
    """Every frame id in the attrs (of groups and variables) and in string variables named
    ``*frame_id`` is ``world`` or a frame the config defines."""
    known = config_frames(cfg)
    problems, n_ids, n_templates = [], 0, 0
    for group, ds in _nodes(obj):
        found = [(f"{group} attr {k}", v) for k, v in ds.attrs.items() if k in FRAME_ATTRS]
        for name, var in ds.variables.items():
            found += [(f"{group}:{name} attr {k}", v) for k, v in var.attrs.items() if k in FRAME_ATTRS]
            if name.endswith("frame_id") and var.dtype.kind in "OUST":
                found += [(f"{group}:{name}", v) for v in np.asarray(var.values).ravel()]
        for where, value in found:
            ids = _expand(str(value), ds)
            if ids is None:
                problems.append(f"{where} = {value!r}: a placeholder with no such coordinate")
                continue
            n_templates += len(ids) > 1 or ids[0] != value
            for fid in ids:
                n_ids += 1
                if fid not in known:
                    problems.append(f"{where} = {fid!r} is not a frame of the config")
    return CheckResult.of(problems, f"{n_ids} frame ids, all known to the frame tree",
                          {"frame_ids_checked": n_ids, "per_element_templates": n_templates,
                           "frames_in_config": len(known)})


# -- passivity ---------------------------------------------------------------------------------------

def element_max_gain_db(pattern: str) -> float:
    if pattern not in ELEMENT_MAX_GAIN_DBI:
        raise ValueError(f"unknown antenna pattern {pattern!r}: known {sorted(ELEMENT_MAX_GAIN_DBI)}")
    return ELEMENT_MAX_GAIN_DBI[pattern]


def free_space_gain_db(distance_m, frequency_hz: float) -> np.ndarray:
    """``20 log10(lambda / (4 pi d))``; +inf at d = 0."""
    lam = SPEED_OF_LIGHT_MPS / frequency_hz
    with np.errstate(divide="ignore"):
        return 20 * np.log10(lam / (4 * np.pi * np.asarray(distance_m, np.float64)))


def _delay_tolerance(los_delay_s):
    return DELAY_TOLERANCE_S + DELAY_TOLERANCE_REL * los_delay_s


def passive_channel(ds: xr.Dataset, tol_db: float = GAIN_TOLERANCE_DB) -> CheckResult:
    """No valid path gains more than free space at the tx-rx distance times the largest element
    gains of the two arrays (``tx_array_pattern``, ``rx_array_pattern``), nor arrives before the
    line of sight: ``|a|^2 <= G_t G_r (lambda / 4 pi d)^2 (+tol_db)`` for every antenna pair, and
    ``tau >= d / c - tolerance``."""
    f = float(ds.attrs["carrier_frequency_hz"])
    g_arrays = (element_max_gain_db(str(ds.attrs.get("tx_array_pattern", "iso")))
                + element_max_gain_db(str(ds.attrs.get("rx_array_pattern", "iso"))))
    d = np.linalg.norm(ds["tx_position_m"].values - ds["rx_position_m"].values, axis=-1)  # time, link
    valid = ds["valid"].values  # time, link, path
    a = ds["a"].values  # time, link, rx_ant, tx_ant, path
    p = (np.abs(a.astype(np.complex128)) ** 2).max(axis=(2, 3))  # the strongest antenna pair
    with np.errstate(divide="ignore"):
        gain_db = 10 * np.log10(p)
    bound_db = free_space_gain_db(d, f)[..., None] + g_arrays
    margin_db = np.where(valid, gain_db - bound_db, -np.inf)
    los_delay = (d / SPEED_OF_LIGHT_MPS)[..., None]
    early_s = np.where(valid, los_delay - ds["tau_s"].values, -np.inf)
    n = int(valid.sum())
    problems = []
    for what, bad in (("gains more than free space by", margin_db > tol_db),
                      ("arrives before the line of sight by", early_s > _delay_tolerance(los_delay))):
        for ti, li, pi in np.argwhere(bad)[:MAX_PROBLEMS]:
            amount = (f"{margin_db[ti, li, pi]:.3f} dB" if "gain" in what else f"{early_s[ti, li, pi] * 1e9:.4f} ns")
            problems.append(f"time {int(ds['time'].values[ti])} ns, link {li}, path {pi} {what} {amount} "
                            f"(d = {d[ti, li]:.2f} m)")
        if bad.sum() > MAX_PROBLEMS:
            problems.append(f"... {int(bad.sum())} paths {what.split(' by')[0]} in all")
    worst = float(margin_db.max()) if n else float("nan")
    earliest = float(early_s.max()) if n else float("nan")
    return CheckResult.of(problems, f"{n} valid paths passive (worst margin {worst:+.2f} dB over free space "
                          f"x {g_arrays:.2f} dBi element gains)",
                          {"paths_checked": n, "worst_margin_db": round(worst, 4) if n else None,
                           "element_gains_db": round(g_arrays, 3), "tolerance_db": tol_db,
                           "largest_delay_before_los_ns": round(earliest * 1e9, 6) if n else None})


def ckm_passive(ds: xr.Dataset, cfg, rows: slice | None = None, cols: slice | None = None,
                tol_db: float = GAIN_TOLERANCE_DB) -> CheckResult:
    """Per station and traced cell (of the tile ``rows`` x ``cols``): ``path_gain_db``, an incoherent
    sum of ``count`` path gains each at most free space times the station's largest element gain
    (the receiver is isotropic, docs/ckm.md), is at most ``FS(d) + G_bs + 10 log10(count)``; and
    ``toa_s >= d / c``. ``d`` is from the station to the cell centre in reference mode, to the
    nearest point of the cell in fast mode (whose gain is a cell mean)."""
    sel = {k: v for k, v in (("y", rows), ("x", cols)) if v is not None}
    ds = ds.isel(sel)
    f = cfg.ofdm.carrier_frequency_hz
    has = ds["enough_hits"].values.astype(bool)  # bs, height, y, x: cells with too few ray hits hold no gain or ToA
    gain = ds["path_gain_db"].values
    count = ds["count"].values.astype(np.float64)
    toa = ds["toa_s"].values
    x, y, h = ds["x"].values, ds["y"].values, ds["height"].values
    stations = {b.name: b for b in cfg.base_stations}
    bss = [stations[str(b)] for b in ds["bs"].values]
    tx = np.array([b.position_m for b in bss], np.float64)  # bs, 3
    g_bs = np.array([element_max_gain_db(b.array.pattern) for b in bss])
    half = 0.0 if cfg.ckm.mode == "reference" else cfg.ckm.cell_size_m / 2
    dx = np.maximum(np.abs(x[None, None, None, :] - tx[:, 0, None, None, None]) - half, 0)
    dy = np.maximum(np.abs(y[None, None, :, None] - tx[:, 1, None, None, None]) - half, 0)
    dz = h[None, :, None, None] - tx[:, 2, None, None, None]
    d = np.sqrt(dx ** 2 + dy ** 2 + dz ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = free_space_gain_db(d, f) + g_bs[:, None, None, None] + 10 * np.log10(np.maximum(count, 1))
        margin = np.where(has, gain - bound, -np.inf)
        early = np.where(has, d / SPEED_OF_LIGHT_MPS - toa, -np.inf)
    n = int(has.sum())
    problems = []
    bad_g = margin > tol_db
    bad_t = early > _delay_tolerance(d / SPEED_OF_LIGHT_MPS)
    for what, bad in (("path_gain_db above free space by", bad_g), ("toa_s before the line of sight", bad_t)):
        for b, hh, i, j in np.argwhere(bad)[:MAX_PROBLEMS]:
            problems.append(f"bs {b}, height {h[hh]:g} m, cell (y {y[i]:g}, x {x[j]:g}): {what}"
                            + (f" {margin[b, hh, i, j]:.3f} dB" if "gain" in what else
                               f" ({early[b, hh, i, j] * 1e9:.4f} ns)"))
    worst = float(margin.max()) if n else float("nan")
    return CheckResult.of(problems, f"{n} station-cell pairs passive (worst margin {worst:+.2f} dB)",
                          {"cells_checked": n, "worst_margin_db": round(worst, 4) if n else None,
                           "tolerance_db": tol_db})


# -- CKM tiles ---------------------------------------------------------------------------------------

def ckm_tile(maps: dict[str, xr.Dataset], cfg, tile: str) -> CheckResult:
    """Tile ``tile`` is marked complete in every map of the scene; fractions of its cells that are
    masked (``cell_masked``: inside a building, outside the region or, fast mode, less than half
    outdoors) and empty (traced, reached by no station), and of its traced cells those holding a path gain and a delay spread from some
    station (fast mode masks each below its own minimum of ray hits: ``ckm.min_hits_for_power``,
    ``min_hits_for_spread`` and their effective-count forms). A tile outside the scene's tiling
    passes with nothing to check."""
    from simart_pipeline.ckm.grid import parse_tile_key, tile_slices
    from simart_pipeline.ckm.maps import masked_cells

    sl = tile_slices(cfg.ckm, tile)
    if sl is None:
        return CheckResult(True, f"tile {tile} is outside the scene's tiling: nothing to check",
                           {"in_scene_tiling": False})
    r, c = parse_tile_key(tile)
    problems, meta = [], {"in_scene_tiling": True, "maps": len(maps)}
    for name, ds in maps.items():
        if not bool(ds["tile_complete"].values[r, c]):
            problems.append(f"map {name}: tile {tile} is not complete")
            continue
        t = ds.isel(y=sl[0], x=sl[1])
        masked = np.broadcast_to(masked_cells(t), t["has_path"].shape[-3:])  # height, y, x
        empty = ~masked & ~t["has_path"].values.astype(bool).any(axis=0)
        meta[f"{name}_cells"] = int(masked.size)
        meta[f"{name}_masked_fraction"] = round(float(masked.mean()), 4)
        meta[f"{name}_empty_fraction"] = round(float(empty.mean()), 4)
        traced = max(int((~masked).sum()), 1)
        for layer, label in (("path_gain_db", "path_gain"), ("rms_delay_spread_s", "delay_spread")):
            held = np.isfinite(t[layer].values).any(axis=0) & ~masked
            meta[f"{name}_with_{label}_fraction"] = round(float(held.sum()) / traced, 4)
    if not maps:
        problems.append("the scene has no channel knowledge map")
    return CheckResult.of(problems, f"tile {tile} complete in {len(maps)} map(s)", meta)
