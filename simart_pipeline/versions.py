"""What each asset partition's content depends on, as digests: code versions, config slices and
data versions (no Dagster import; the assets hand these to Dagster).

- **Code version** of an asset: SHA-256 over the source of its asset module and of every project
  module its science entry points import, transitively (read from the code's own imports). It
  changes when the asset's logic changes, and only then.
- **Config slice** of a stage: the part of ``scene.yaml`` the stage reads, as canonical JSON. A
  sensor's rate is in the ``sensor_frames`` slice only; the rain materials only in the rainy radio
  slices; the CKM grid only in the CKM slices.
- **Source files** a stage reads: the OSM or mesh file (``osm_extract``), replay recordings
  (``trajectory``), imported bags (``sensor_frames``), the codebook file (``kpis``, ``ckm_layers``),
  each by the SHA-256 of its bytes.
- **Data version** of an asset partition: SHA-256 of the asset, its partition key, its code
  version, its config slice, its source files and the data versions of its upstream partitions.
  It is computed from the inputs alone, before anything runs, so equal inputs give an equal data
  version on any machine, and ``simart run`` knows what is up to date without opening a store.
"""

from __future__ import annotations

import ast
import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from simart_pipeline.ckm.grid import scene_tiles
from simart_pipeline.config import SceneConfig
from simart_pipeline.radio.materials import WEATHER_GROUP

PACKAGE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Stage:
    """One asset: its science entry points (for the code version) and its partitioning."""

    entry_modules: tuple[str, ...]
    partitioned_by: str  # "scene", or the second dimension: "weather", "weather_group" or "tile"


STAGES: dict[str, Stage] = {
    "osm_extract": Stage(("simart_pipeline.scene.source", "simart_pipeline.scene.geometry"), "scene"),
    "paired_meshes": Stage(("simart_pipeline.scene.build",), "scene"),
    "trajectory": Stage(("simart_pipeline.mobility.trajectory", "simart_pipeline.mobility.replay"), "scene"),
    "sensor_frames": Stage(("simart_pipeline.sensing.sensor_frames",), "weather"),
    "cirs": Stage(("simart_pipeline.radio.cirs", "simart_pipeline.radio.tracer"), "weather_group"),
    "radar_frames": Stage(("simart_pipeline.radio.radar_echoes",), "weather_group"),
    "kpis": Stage(("simart_pipeline.link.kpis", "simart_pipeline.link.beams"), "weather"),
    "ckm_layers": Stage(("simart_pipeline.ckm.layers", "simart_pipeline.ckm.mosaic", "simart_pipeline.ckm.maps",
                         "simart_pipeline.ckm.one_pass"), "tile"),
    "ckm_map": Stage(("simart_pipeline.ckm.maps", "simart_pipeline.previews"), "scene"),
    "session": Stage((), "weather"),
    "session_bag": Stage(("simart_pipeline.export.bag", "simart_pipeline.export.pictures"), "weather"),
    "beam_prediction": Stage(("simart_pipeline.study.beam_prediction",), "scene"),
}
ASSET_MODULE = {"osm_extract": "scene", "paired_meshes": "scene", "trajectory": "scene",
                "sensor_frames": "sensing", "cirs": "radio", "radar_frames": "radio", "kpis": "link", "ckm_layers": "ckm",
                "ckm_map": "ckm", "session": "session",
                "session_bag": "session", "beam_prediction": "study"}


# --- code versions --------------------------------------------------------------------------------
def _module_path(name: str) -> Path | None:
    parts = name.split(".")[1:]
    if not parts:
        return PACKAGE / "__init__.py"
    rel = Path(*parts)
    for p in (PACKAGE / rel.with_suffix(".py"), PACKAGE / rel / "__init__.py"):
        if p.is_file():
            return p
    return None


@lru_cache(maxsize=None)
def _project_imports(name: str) -> tuple[str, ...]:
    """The project modules that module ``name`` imports (module level and inside functions)."""
    path = _module_path(name)
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            cands = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            cands = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
        else:
            continue
        out.update(c for c in cands if c.startswith("simart_pipeline") and _module_path(c) is not None)
    return tuple(sorted(out))


def import_closure(roots) -> list[str]:
    """Every project module reachable from ``roots`` through imports, sorted."""
    seen, todo = set(), list(roots)
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(_project_imports(m))
    return sorted(seen)


@lru_cache(maxsize=None)
def code_version(asset: str) -> str:
    """SHA-256 (first 16 hex digits) of the asset module and its entry points' import closure."""
    stage = STAGES[asset]
    h = hashlib.sha256()
    modules = sorted(set(import_closure(stage.entry_modules))
                     | {f"simart_pipeline.assets.{ASSET_MODULE[asset]}"})
    for m in modules:
        h.update(m.encode())
        h.update(_module_path(m).read_bytes())
    return h.hexdigest()[:16]


# --- config slices --------------------------------------------------------------------------------
def _without(d: dict, *keys) -> dict:
    return {k: v for k, v in d.items() if k not in keys}


def _devices(raw: dict, *, sensors: bool, actors: bool = True) -> dict:
    """Base stations and platforms with or without their sensors (and radars), with or without the
    actors' bodies and the static actors."""
    drop_b = () if sensors else ("sensors", "radar")
    drop_p = (() if sensors else ("sensors",)) + (() if actors else ("body",))
    out = {"base_stations": [_without(b, *drop_b) for b in raw["base_stations"]],
           "platforms": [_without(p, *drop_p) for p in raw["platforms"]]}
    if actors:
        out["static_actors"] = raw["static_actors"]
    return out


def config_slice(cfg: SceneConfig, asset: str, sub: str | None = None) -> dict:
    """The part of the scene config that ``asset`` reads for partition ``sub`` (weather or tile)."""
    raw = cfg.model_dump(mode="json")
    clock = raw["clock"]
    dry_materials = _without(raw["materials"], "rain")  # what the scene is built with
    if asset == "osm_extract":
        return {"source": raw["source"], "origin": raw["origin"], "materials": dry_materials}
    if asset == "paired_meshes":
        return {"source": raw["source"], "origin": raw["origin"], "materials": dry_materials,
                "carrier_frequency_hz": raw["ofdm"]["carrier_frequency_hz"]}
    if asset == "trajectory":
        return {"platforms": [_without(p, "sensors", "array", "body") for p in raw["platforms"]],
                "clock": {k: clock[k] for k in ("duration_s", "pose_rate_hz")}}
    if asset == "sensor_frames":
        return {**_devices(raw, sensors=True), "sensor_imports": raw["sensor_imports"], "seed": raw["seed"],
                "origin": raw["origin"], "duration_s": clock["duration_s"], "weather": sub}
    if asset == "cirs":  # sub: a weather group
        return {**_devices(raw, sensors=False), **{k: raw[k] for k in ("ray_tracing", "ofdm")},
                "materials": dry_materials, "weather_materials": cfg.materials.weather_table()[sub],
                "clock": {k: clock[k] for k in ("duration_s", "radio_rate_hz")}}
    if asset == "radar_frames":  # sub: a weather group; a scene without radar reads nothing
        if not any(b.radar for b in cfg.base_stations):
            return {"radars": None}
        return {"base_stations": raw["base_stations"],
                "platforms": [_without(p, "sensors", "array") for p in raw["platforms"]],
                "static_actors": raw["static_actors"], **{k: raw[k] for k in ("ray_tracing", "ofdm")},
                "materials": dry_materials, "weather_materials": cfg.materials.weather_table()[sub],
                "duration_s": clock["duration_s"]}
    if asset == "kpis":
        return {**{k: raw[k] for k in ("ofdm", "link", "receiver", "codebook", "seed")}, "weather": sub}
    if asset == "ckm_layers":  # the map of the static scene: no actor
        return {**_devices(raw, sensors=False, actors=False),
                **{k: raw[k] for k in ("ckm", "ray_tracing", "ofdm", "link", "receiver", "codebook",
                                       "materials", "weathers")}, "tile": sub}
    if asset == "ckm_map":
        return {"ckm": raw["ckm"], "weathers": raw["weathers"]}
    if asset == "session":
        return {"duration_s": clock["duration_s"], "weather": sub}
    if asset == "session_bag":  # the frame tree (mounts, base station poses, bodies) and the origin
        mounts = lambda d: [(s["name"], s["kind"], s["mount"]) for s in d["sensors"]]  # noqa: E731
        return {"base_stations": [(b["name"], b["position_m"], b["orientation_deg"], mounts(b))
                                  for b in raw["base_stations"]],
                "platforms": [(p["name"], p["body"], mounts(p)) for p in raw["platforms"]],
                "static_actors": raw["static_actors"], "origin": raw["origin"], "weather": sub}
    if asset == "beam_prediction":  # a scene without a study reads nothing
        return {"beam_study": raw["beam_study"], "weathers": raw["weathers"] if raw["beam_study"] else None}
    raise KeyError(f"unknown asset {asset!r}")


# --- source files ---------------------------------------------------------------------------------
@lru_cache(maxsize=256)
def _file_digest(path: str, mtime_ns: int, size: int) -> str:
    h = hashlib.sha256()
    p = Path(path)
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    for f in files:
        h.update(str(f.relative_to(p) if p.is_dir() else f.name).encode())
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (a directory: of its files' names and bytes); cached per mtime."""
    p = Path(path)
    if not p.exists():
        return "missing"
    st = p.stat()
    return _file_digest(str(p.resolve()), st.st_mtime_ns, st.st_size)


def source_files(cfg: SceneConfig, asset: str, scene_dir: Path | None) -> dict[str, str]:
    """``{path relative to the scene: digest}`` of the files ``asset`` reads besides the config."""
    if scene_dir is None:
        return {}
    names = []
    if asset == "osm_extract" and cfg.source.kind in ("osm", "mesh", "sionna_xml"):
        names.append(cfg.source.path)
    if asset == "osm_extract" and cfg.source.kind == "sionna_xml":  # and the meshes it names
        from simart_pipeline.scene.sionna_xml import referenced_files

        names += referenced_files(Path(scene_dir), cfg.source.path)
    if asset == "trajectory":
        names += [p.trajectory.path for p in cfg.platforms if p.trajectory.kind == "replay"]
    if asset == "sensor_frames":
        names += [imp.path for imp in cfg.sensor_imports]
    if asset in ("sensor_frames", "cirs", "session_bag") or (
            asset == "radar_frames" and any(b.radar for b in cfg.base_stations)):
        names += [a.body.mesh for a in (*cfg.platforms, *cfg.static_actors) if a.body.is_file]
    if asset in ("kpis", "ckm_layers") and cfg.codebook.path:
        names.append(cfg.codebook.path)
    return {n: file_digest(Path(scene_dir) / n) for n in sorted(set(names))}


# --- data versions --------------------------------------------------------------------------------
def upstream(cfg: SceneConfig, asset: str, sub: str | None) -> list[tuple[str, str | None]]:
    """The upstream (asset, sub-key) partitions of one asset partition."""
    if asset == "osm_extract":
        return []
    if asset == "paired_meshes":
        return [("osm_extract", None)]
    if asset == "trajectory":
        return [("osm_extract", None)]
    if asset == "sensor_frames":
        return [("paired_meshes", None), ("trajectory", None)]
    if asset == "cirs":
        return [("paired_meshes", None), ("trajectory", None), ("osm_extract", None)]
    if asset == "radar_frames":
        return [("paired_meshes", None), ("trajectory", None)] if any(b.radar for b in cfg.base_stations) else []
    if asset == "kpis":
        return [("cirs", WEATHER_GROUP[sub])]
    if asset == "ckm_layers":
        return [("paired_meshes", None), ("osm_extract", None)]
    if asset == "ckm_map":
        return [("osm_extract", None)] + [("ckm_layers", t) for t in scene_tiles(cfg.ckm)]
    if asset == "session":
        return [("trajectory", None), ("sensor_frames", sub), ("cirs", WEATHER_GROUP[sub]), ("kpis", sub)]
    if asset == "session_bag":  # and the CKM map of its radio materials (VersionPlan.inputs)
        return [("session", sub), ("radar_frames", WEATHER_GROUP[sub])]
    if asset == "beam_prediction":
        if cfg.beam_study is None:
            return []
        return [("trajectory", None)] + [(a, w) for w in cfg.weathers for a in ("sensor_frames", "kpis")]
    raise KeyError(f"unknown asset {asset!r}")


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


class VersionPlan:
    """Data versions of every asset partition of one scene, computed once per config."""

    def __init__(self, cfg: SceneConfig, scene_dir: Path | None):
        self.cfg, self.scene_dir = cfg, scene_dir
        self._memo: dict[tuple[str, str | None], str] = {}

    def inputs(self, asset: str, sub: str | None = None) -> dict:
        """Everything the data version of ``(asset, sub)`` digests, by name (for 'why stale')."""
        return {"asset": asset, "partition": [self.cfg.name, sub], "code_version": code_version(asset),
                "config": _digest(config_slice(self.cfg, asset, sub)),
                "source_files": source_files(self.cfg, asset, self.scene_dir),
                "upstream": {f"{a}[{s}]" if s else a: self.data_version(a, s)
                             for a, s in upstream(self.cfg, asset, sub)}
                | ({f"ckm_map[{WEATHER_GROUP[sub]}]": self.map_version(WEATHER_GROUP[sub])}
                   if asset == "session_bag" else {})}

    def config_version(self, asset: str, sub: str | None = None) -> str:
        """Digest of the config slice and the source files of ``(asset, sub)``: the data version of
        its ``scene_config`` source asset in Dagster."""
        return _digest({"config": config_slice(self.cfg, asset, sub),
                        "source_files": source_files(self.cfg, asset, self.scene_dir)})[:32]

    def data_version(self, asset: str, sub: str | None = None) -> str:
        key = (asset, sub)
        if key not in self._memo:
            self._memo[key] = _digest(self.inputs(asset, sub))[:32]
        return self._memo[key]

    def map_version(self, name: str) -> str:
        """Version of one channel knowledge map (``name``: a set of radio materials, e.g. sunny):
        the CKM code, the config the map reads with that set's materials only, and the scene's
        meshes and geometry. A change of the rain materials leaves the dry map's version as it is."""
        raw = config_slice(self.cfg, "ckm_layers", None)
        raw["materials"] = _without(raw["materials"], "rain")
        raw["weather_materials"] = self.cfg.materials.weather_table()[name]
        return _digest({"map": name, "code_version": code_version("ckm_layers"), "config": raw,
                        "source_files": source_files(self.cfg, "ckm_layers", self.scene_dir),
                        "upstream": [self.data_version("paired_meshes"), self.data_version("osm_extract")]})[:32]

    def map_tile_version(self, name: str, tile: str) -> int:
        """Version of one tile of one map, as a non-negative int64 (stored per tile in the mosaic)."""
        return int(_digest([self.map_version(name), tile])[:15], 16)


def why_different(old: dict | None, new: dict) -> str:
    """A short cause: which inputs of a data version changed (``old``: the stored inputs)."""
    if not old:
        return "missing"
    causes = []
    if old.get("code_version") != new["code_version"]:
        causes.append("code changed")
    if old.get("config") != new["config"]:
        causes.append("its config changed")
    if old.get("source_files") != new["source_files"]:
        causes.append("a source file changed")
    changed = sorted(k for k in set(old.get("upstream", {})) | set(new["upstream"])
                     if old.get("upstream", {}).get(k) != new["upstream"].get(k))
    if changed:
        causes.append("upstream " + ", ".join(changed) + " changed")
    return "; ".join(causes) or "inputs changed"
