"""Sionna RT PathSolver, called one way: load a radio scene, place devices, trace, sort paths.

Everything the project traces goes through :class:`RadioScene.trace`, which batches receivers into
as few solver calls as ``ray_tracing.max_receivers_per_call`` allows, runs the solver in its
deterministic mode with the configured seed, and returns paths sorted per (receiver, transmitter):
valid first, then by delay, then by interaction sequence, so that two runs compare entry by entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from simart_pipeline import engine
from simart_pipeline.config import Array, SceneConfig

# Weather changes radio materials (first version): rain wets the ground. ITU-R P.2040-3 Table 3
# gives wet_ground for 1-10 GHz; the wet-facade material is the ray-tracing issue's refinement.
WEATHER_MATERIAL_OVERRIDES: dict[str, dict[str, str]] = {
    "sunny": {},
    "night": {},
    "rainy": {"medium_dry_ground": "wet_ground", "very_dry_ground": "wet_ground"},
}
RX_NEAR_TX_M = 0.01  # Sionna RT silently drops the LoS path of a receiver this close to a transmitter


@dataclass
class TracedPaths:
    """Sorted paths of ``num_rx`` receivers and ``num_tx`` transmitters (numpy, float32 as Sionna)."""

    a: np.ndarray            # [num_rx, rx_ant, num_tx, tx_ant, path] complex64
    tau_s: np.ndarray        # [num_rx, num_tx, path] float64, NaN where invalid
    theta_t: np.ndarray      # [num_rx, num_tx, path] rad, world frame; NaN where invalid
    phi_t: np.ndarray
    theta_r: np.ndarray
    phi_r: np.ndarray
    doppler_hz: np.ndarray   # [num_rx, num_tx, path]
    interaction: np.ndarray  # [num_rx, num_tx, depth, path] uint8
    valid: np.ndarray        # [num_rx, num_tx, path] bool

    @property
    def los(self) -> np.ndarray:
        return self.valid & np.all(self.interaction == 0, axis=-2)


def sionna_array(array: Array):
    import sionna.rt as rt

    return rt.PlanarArray(num_rows=array.rows, num_cols=array.cols,
                          vertical_spacing=array.spacing_wavelengths,
                          horizontal_spacing=array.spacing_wavelengths,
                          pattern=array.pattern, polarization=array.polarization)


class RadioScene:
    """A Sionna RT scene loaded once, with the config's frequency, arrays and weather materials."""

    def __init__(self, scene_xml: str | Path | None, cfg: SceneConfig, weather: str = "sunny"):
        engine.init()
        import sionna.rt as rt

        self.cfg = cfg
        self.weather = weather
        self.scene = rt.load_scene(str(scene_xml), merge_shapes=False) if scene_xml else rt.load_scene()
        self.scene.frequency = cfg.ofdm.carrier_frequency_hz
        self.scene.bandwidth = cfg.ofdm.bandwidth_hz
        self.scene.tx_array = sionna_array(cfg.base_stations[0].array)
        self.scene.rx_array = sionna_array(cfg.platforms[0].array)
        self.material_overrides = self._apply_weather(weather)

    def _apply_weather(self, weather: str) -> dict[str, str]:
        import sionna.rt as rt

        overrides = WEATHER_MATERIAL_OVERRIDES[weather]
        applied = {}
        new = {}
        for name, obj in sorted(self.scene.objects.items()):
            itu = getattr(obj.radio_material, "itu_type", None)
            if itu in overrides:
                target = overrides[itu]
                if target not in new:
                    new[target] = rt.ITURadioMaterial(f"itu_{target}_{weather}", target,
                                                      thickness=self.cfg.materials.thickness_m)
                obj.radio_material = new[target]
                applied[name] = f"{itu} -> {target}"
        return applied

    @property
    def wavelength_m(self) -> float:
        return float(np.array(self.scene.wavelength).ravel()[0])

    def array_positions_m(self, which: str) -> np.ndarray:
        """Antenna positions [num_ant, 3] in the device's own frame (boresight +x)."""
        arr = self.scene.tx_array if which == "tx" else self.scene.rx_array
        return np.array(arr.positions(self.wavelength_m)).T.astype(np.float64)

    def radio_materials(self) -> dict[str, str]:
        return {name: getattr(obj.radio_material, "itu_type", obj.radio_material.name)
                for name, obj in sorted(self.scene.objects.items())}

    def trace(self, tx_positions: np.ndarray, tx_orientations_rad: np.ndarray,
              rx_positions: np.ndarray, rx_velocities: np.ndarray | None = None,
              rx_orientations_rad: np.ndarray | None = None,
              tx_velocities: np.ndarray | None = None) -> TracedPaths:
        """Trace all transmitters to all receivers.

        :param tx_positions: [num_tx, 3] m, world; ``tx_orientations_rad`` [num_tx, 3] (yaw, pitch, roll)
        :param rx_positions: [num_rx, 3] m; ``rx_velocities`` [num_rx, 3] m/s;
            ``rx_orientations_rad`` [num_rx, 3]
        """
        import sionna.rt as rt

        rt_cfg = self.cfg.ray_tracing
        solver = rt.PathSolver()
        num_rx = len(rx_positions)
        if num_rx == 0:
            raise ValueError("no receiver to trace")
        for i, (p, o) in enumerate(zip(tx_positions, tx_orientations_rad)):
            v = None if tx_velocities is None else tx_velocities[i]
            self.scene.add(rt.Transmitter(f"tx{i}", position=[float(c) for c in p],
                                          orientation=[float(c) for c in o],
                                          velocity=None if v is None else [float(c) for c in v]))
        chunks = []
        try:
            step = rt_cfg.max_receivers_per_call
            for start in range(0, num_rx, step):
                idx = range(start, min(start + step, num_rx))
                for i in idx:
                    kw = {}
                    if rx_velocities is not None:
                        kw["velocity"] = [float(c) for c in rx_velocities[i]]
                    if rx_orientations_rad is not None:
                        kw["orientation"] = [float(c) for c in rx_orientations_rad[i]]
                    self.scene.add(rt.Receiver(f"rx{i}", position=[float(c) for c in rx_positions[i]], **kw))
                paths = solver(self.scene, max_depth=rt_cfg.max_depth,
                               max_num_paths_per_src=rt_cfg.max_num_paths_per_src,
                               samples_per_src=rt_cfg.samples_per_src, synthetic_array=True,
                               los=rt_cfg.los, specular_reflection=rt_cfg.specular_reflection,
                               diffuse_reflection=rt_cfg.diffuse_reflection,
                               refraction=rt_cfg.refraction, seed=rt_cfg.seed)
                chunks.append(_to_numpy(paths, len(tx_positions), len(idx), rt_cfg.max_depth,
                                        self.scene.rx_array.num_ant, self.scene.tx_array.num_ant))
                for i in idx:
                    self.scene.remove(f"rx{i}")
        finally:
            for i in range(len(tx_positions)):
                self.scene.remove(f"tx{i}")
            for name in list(self.scene.receivers):
                self.scene.remove(name)
        return _sort(_concat(chunks))


def _to_numpy(paths, num_tx: int, num_rx: int, max_depth: int, rx_ant: int, tx_ant: int) -> dict[str, np.ndarray]:
    # Explicit shapes: Sionna squeezes nothing, but a call with no path has zero-size arrays.
    num_paths = np.array(paths.tau).shape[-1]
    shape = (num_rx, num_tx, num_paths)
    a = np.array(paths.a[0]) + 1j * np.array(paths.a[1])
    out = {
        "a": a.astype(np.complex64).reshape(num_rx, rx_ant, num_tx, tx_ant, num_paths),
        "tau_s": np.array(paths.tau).astype(np.float64).reshape(shape),
        "theta_t": np.array(paths.theta_t).reshape(shape),
        "phi_t": np.array(paths.phi_t).reshape(shape),
        "theta_r": np.array(paths.theta_r).reshape(shape),
        "phi_r": np.array(paths.phi_r).reshape(shape),
        "doppler_hz": np.array(paths.doppler).reshape(shape),
        "valid": np.array(paths.valid).astype(bool).reshape(shape),
    }
    inter = np.array(paths.interactions).astype(np.uint8)
    inter = inter.reshape(max_depth, num_rx, num_tx, num_paths) if max_depth else \
        np.zeros((0, num_rx, num_tx, num_paths), np.uint8)
    out["interaction"] = np.moveaxis(inter, 0, 2)  # [rx, tx, depth, path]
    return out


def _concat(chunks: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Pad every chunk to the largest path count, then join along receivers."""
    n = max(c["tau_s"].shape[-1] for c in chunks)
    padded = []
    for c in chunks:
        k = n - c["tau_s"].shape[-1]
        d = {}
        for key, v in c.items():
            fill = {"valid": False, "a": 0, "interaction": 0}.get(key, -1 if key == "tau_s" else 0)
            d[key] = np.pad(v, [(0, 0)] * (v.ndim - 1) + [(0, k)], constant_values=fill)
        padded.append(d)
    return {key: np.concatenate([c[key] for c in padded], axis=0) for key in padded[0]}


def _sort(d: dict[str, np.ndarray]) -> TracedPaths:
    valid = d["valid"]
    tau = np.where(valid, d["tau_s"], np.inf)
    inter = d["interaction"]  # [rx, tx, depth, path]
    # np.lexsort: the last key is the primary one.
    keys = [inter[:, :, k, :] for k in range(inter.shape[2] - 1, -1, -1)] + [tau, ~valid]
    order = np.lexsort(keys, axis=-1)  # [rx, tx, path]

    def take(v):
        if v.ndim == 3:  # [rx, tx, path]
            return np.take_along_axis(v, order, axis=-1)
        if v.ndim == 4:  # interaction [rx, tx, depth, path]
            return np.take_along_axis(v, order[:, :, None, :], axis=-1)
        return np.take_along_axis(v, order[:, None, :, None, :], axis=-1)  # a [rx, rx_ant, tx, tx_ant, path]

    valid_s = take(valid)
    nan = np.float64(np.nan)
    out = {k: take(v) for k, v in d.items()}
    for k in ("tau_s", "theta_t", "phi_t", "theta_r", "phi_r", "doppler_hz"):
        out[k] = np.where(valid_s, out[k], nan).astype(np.float64 if k == "tau_s" else np.float32)
    out["a"] = np.where(valid_s[:, None, :, None, :], out["a"], 0).astype(np.complex64)
    out["interaction"] = np.where(valid_s[:, :, None, :], out["interaction"], 0).astype(np.uint8)
    out["valid"] = valid_s
    return TracedPaths(**out)
