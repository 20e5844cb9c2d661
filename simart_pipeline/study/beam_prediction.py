"""Vision- and position-aided beam prediction (``docs/beam-study.md``), after the paper's case study.

A rooftop base station's camera sees a UAV; the UAV is detected in each rendered RGB frame, and its
image position and box size, with the UAV's GPS fix, predict the best beam of the base station's
codebook. Everything here works on arrays read from the stores; no Dagster.

- **Samples**: the instants where the camera has a frame and the radio a channel (the shared clock),
  per weather. Label: that weather's ``best_beam`` of the (base station, UAV) link.
- **Flights**: the legs of the UAV's waypoint trajectory; the split is by flight, so no frame of a
  test flight is seen in training.
- **Detectors**: ``difference`` (trained here: a per-weather background image and noise level from
  the training flights' frames, then a random forest that scores each changed blob, tuned by
  flight-grouped cross-validation) and ``mog2`` (the classical baseline: OpenCV's adaptive Gaussian
  mixture background subtraction, largest blob). Neither sees ground truth at test time.
- **Beam classifiers**: random forests on position only (GPS), vision only (detected box), both, and
  the ground-truth box instead of the detector's, alone and with position (the ceilings), trained
  on the training flights of every weather together and evaluated per weather.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PAPER_TOP_K = {  # the paper's table: top-1, top-3, top-5 (%)
    "sunny": (97.86, 99.83, 100.00), "rainy": (95.39, 99.84, 100.00), "night": (97.92, 99.94, 100.00)}
TOP_K = (1, 3, 5)
FEATURE_SETS = ("position", "vision", "position+vision", "truth_box", "position+truth_box")
DETECTORS = ("difference", "mog2")
BOX_CORNERS = ("u_min", "v_min", "u_max", "v_max")


@dataclass
class WeatherSamples:
    """One weather's samples on the shared clock, in time order."""

    weather: str
    time_ns: np.ndarray         # [N] int64
    flight: np.ndarray          # [N] int: the leg of the trajectory
    best_beam: np.ndarray       # [N] int: the label
    beam_gain_db: np.ndarray    # [N, beams]
    rgb: np.ndarray             # [N, H, W, 3] uint8
    truth_box_px: np.ndarray    # [N, 4] u_min, v_min, u_max, v_max of the visible pixels; NaN: not visible
    gps_enu_m: np.ndarray       # [N, 3] the latest valid fix at or before the instant


# --- flights --------------------------------------------------------------------------------------
def waypoint_passage_times(time_ns: np.ndarray, position_m: np.ndarray, waypoints_m: np.ndarray,
                           tolerance_m: float) -> np.ndarray:
    """Time (ns) at which the path passes each interior waypoint, in order: the closest approach in
    the first stretch after the previous passage that comes within ``tolerance_m`` + 0.5 m of it
    (the path cuts corners by at most the waypoint tolerance); the closest approach overall after
    the previous passage if none does."""
    out, start = [], 0
    for w in np.asarray(waypoints_m)[1:-1]:
        d = np.linalg.norm(position_m[start:] - w, axis=1)
        near = np.flatnonzero(d <= tolerance_m + 0.5)
        if near.size:
            first = near[0]
            end = first + int(np.argmax(d[first:] > tolerance_m + 0.5)) if (d[first:] > tolerance_m + 0.5).any() \
                else d.size
            k = first + int(np.argmin(d[first:end]))
        else:
            k = int(np.argmin(d))
        start += k
        out.append(time_ns[start])
    return np.asarray(out, dtype=np.int64)


def flight_of(time_ns: np.ndarray, passages_ns: np.ndarray) -> np.ndarray:
    """Leg index of each instant: 0 before the first interior waypoint, and so on."""
    return np.searchsorted(passages_ns, time_ns, side="right")


def split_flights(num_flights: int, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(training flights, test flights), sorted; at least one of each."""
    if num_flights < 2:
        raise ValueError(f"the study needs at least two flights, the trajectory has {num_flights}")
    order = np.random.default_rng(seed).permutation(num_flights)
    n_test = min(num_flights - 1, max(1, int(round(test_fraction * num_flights))))
    return np.sort(order[n_test:]), np.sort(order[:n_test])


# --- detection ------------------------------------------------------------------------------------
@dataclass
class Detections:
    """Per frame: the box (NaN where nothing is detected)."""

    box_px: np.ndarray  # [N, 4]

    @property
    def found(self) -> np.ndarray:
        return np.isfinite(self.box_px[:, 0])


def box_centre(box: np.ndarray) -> np.ndarray:
    return np.stack([(box[..., 0] + box[..., 2]) / 2, (box[..., 1] + box[..., 3]) / 2], axis=-1)


def correct(det_box: np.ndarray, truth_box: np.ndarray, margin_px: float) -> np.ndarray:
    """True where a detected box's centre lies in the visible truth box grown by ``margin_px``."""
    c = box_centre(det_box)
    with np.errstate(invalid="ignore"):
        return ((c[:, 0] >= truth_box[:, 0] - margin_px) & (c[:, 0] <= truth_box[:, 2] + margin_px)
                & (c[:, 1] >= truth_box[:, 1] - margin_px) & (c[:, 1] <= truth_box[:, 3] + margin_px))


def _difference(rgb: np.ndarray, background: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.absdiff(rgb, background).max(axis=-1)


def background_model(frames: np.ndarray, max_frames: int = 240) -> tuple[np.ndarray, float]:
    """(per-pixel median image, noise level) of a fixed camera's frames: the median over frames in
    which the UAV moves leaves the static scene; the noise level is 1.4826 × the median absolute
    difference of the frames to it (a robust σ of sensor noise and rain streaks)."""
    idx = np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).astype(int)
    bg = np.median(frames[idx], axis=0).astype(np.uint8)
    sigma = 1.4826 * float(np.median(np.stack([_difference(frames[i], bg) for i in idx[:: max(1, len(idx) // 40)]])))
    return bg, max(sigma, 1.0)


BLOB_FEATURES = ("area_px", "width_px", "height_px", "peak_difference", "mean_difference", "u_norm", "v_norm",
                 "mean_r", "mean_g", "mean_b", "background_brightness", "difference_over_noise")


def blobs(rgb: np.ndarray, background: np.ndarray, sigma: float, k_sigma: float = 5.0,
          max_blobs: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Changed blobs of one frame: (boxes [M, 4] u_min, v_min, u_max, v_max in px, features
    [M, len(BLOB_FEATURES)]), at most the ``max_blobs`` with the highest peak difference. The cap is
    high: in rain a frame holds dozens of streaks, each a blob larger than a far UAV."""
    import cv2
    from scipy import ndimage

    diff = _difference(rgb, background)
    mask = (diff > max(6.0, k_sigma * sigma)).astype(np.uint8)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros((0, 4)), np.zeros((0, len(BLOB_FEATURES)))
    h, w = diff.shape
    index = np.arange(1, n)
    d = diff.astype(np.float64)
    peak = ndimage.maximum(d, labels, index)
    keep = np.argsort(-peak, kind="stable")[:max_blobs]
    index, peak = index[keep], peak[keep]
    x, y, bw, bh, area = (stats[index, c].astype(float) for c in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                                  cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT,
                                                                  cv2.CC_STAT_AREA))
    mean_d = ndimage.mean(d, labels, index)
    colour = [ndimage.mean(rgb[..., c].astype(np.float64), labels, index) for c in range(3)]
    bright = ndimage.mean(background.astype(np.float64).mean(axis=-1), labels, index)
    boxes = np.stack([x, y, x + bw, y + bh], axis=1)
    feats = np.stack([area, bw, bh, peak, mean_d, (x + bw / 2) / w, (y + bh / 2) / h, *colour, bright,
                      peak / sigma], axis=1)
    return boxes, feats


class DifferenceDetector:
    """Background difference with a learnt blob scorer (see the module docstring)."""

    def __init__(self, seed: int = 0, margin_px: float = 4.0):
        self.seed, self.margin_px = seed, margin_px
        self.background: dict[str, tuple[np.ndarray, float]] = {}
        self.threshold = 0.5
        self._blobs: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}

    def _frame_blobs(self, s: WeatherSamples, i: int):
        key = (s.weather, int(s.time_ns[i]))
        if key not in self._blobs:
            self._blobs[key] = blobs(s.rgb[i], *self.background[s.weather])
        return self._blobs[key]

    def fit(self, train: list[WeatherSamples], train_mask: list[np.ndarray]) -> "DifferenceDetector":
        from sklearn.ensemble import RandomForestClassifier
        from sklearn.model_selection import GroupKFold, cross_val_predict

        X, y, groups, frame_id = [], [], [], []
        fid = 0
        for s, m in zip(train, train_mask):
            self.background[s.weather] = background_model(s.rgb[m])
            for i in np.flatnonzero(m):
                boxes, f = self._frame_blobs(s, i)
                if len(f):
                    X.append(f)
                    y.append(correct(boxes, np.repeat(s.truth_box_px[i:i + 1], len(boxes), 0), self.margin_px))
                    groups.append(np.full(len(f), s.flight[i]))
                    frame_id.append(np.full(len(f), fid))
                fid += 1
        X, y, groups, frame_id = (np.concatenate(a) for a in (X, y, groups, frame_id))
        self.model = RandomForestClassifier(n_estimators=200, min_samples_leaf=2, random_state=self.seed,
                                            class_weight="balanced", n_jobs=1)
        # The score threshold: the one that maximises correct minus false detections on held-out
        # flights (grouped cross-validation), one detection (the best blob) per frame.
        if not y.any():
            raise ValueError("detector training: no changed blob of the training frames is the UAV; "
                             "check that the camera sees the flights")
        if y.all():  # nothing but the UAV ever changes: every blob is it
            from sklearn.dummy import DummyClassifier

            self.model, self.threshold = DummyClassifier(strategy="prior").fit(X, y), 0.5
            return self
        folds = min(4, len(np.unique(groups)))
        if folds < 2:
            raise ValueError("detector training: the training frames come from one flight; at least two are needed")
        oof = cross_val_predict(self.model, X, y, groups=groups, cv=GroupKFold(n_splits=folds),
                                method="predict_proba")[:, 1]
        best = {}
        for f in np.unique(frame_id):
            sel = np.flatnonzero(frame_id == f)
            j = sel[np.argmax(oof[sel])]
            best[f] = (oof[j], y[j])
        scores = np.array([v[0] for v in best.values()])
        hits = np.array([v[1] for v in best.values()])
        cands = np.unique(np.round(scores, 3))
        gain = [(hits[scores >= t].sum() - (~hits[scores >= t]).sum()) for t in cands]
        self.threshold = float(cands[int(np.argmax(gain))]) if len(cands) else 0.5
        self.model.fit(X, y)
        return self

    def detect(self, s: WeatherSamples, mask: np.ndarray) -> Detections:
        out = np.full((len(s.time_ns), 4), np.nan)
        frames = [(i, *self._frame_blobs(s, i)) for i in np.flatnonzero(mask)]
        frames = [f for f in frames if len(f[2])]
        if not frames:
            return Detections(out)
        p = self.model.predict_proba(np.concatenate([f[2] for f in frames]))[:, -1]
        start = 0
        for i, boxes, f in frames:  # the best blob of each frame, if it scores above the threshold
            q = p[start:start + len(f)]
            start += len(f)
            j = int(np.argmax(q))
            if q[j] >= self.threshold:
                out[i] = boxes[j]
        return Detections(out)


def mog2_detect(s: WeatherSamples, mask: np.ndarray, warmup: np.ndarray) -> Detections:
    """The classical baseline: OpenCV's MOG2 background subtractor run through each flight's frames
    in time order (after ``warmup`` frames of the same camera and weather), the largest foreground
    blob of each frame after a 2 × 2 opening (it removes single-pixel noise and keeps a far UAV, which
    may be only two pixels tall; a 3 × 3 opening erases it)."""
    import cv2

    out = np.full((len(s.time_ns), 4), np.nan)
    kernel = np.ones((2, 2), np.uint8)
    for f in np.unique(s.flight[mask]):
        mog = cv2.createBackgroundSubtractorMOG2(history=50, varThreshold=16, detectShadows=False)
        for frame in warmup:
            mog.apply(frame)
        for i in np.flatnonzero(mask & (s.flight == f)):
            fg = cv2.morphologyEx((mog.apply(s.rgb[i]) > 0).astype(np.uint8), cv2.MORPH_OPEN, kernel)
            n, _, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
            if n > 1:
                c = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
                x, y, w, h, _ = stats[c]
                out[i] = (x, y, x + w, y + h)
    return Detections(out)


def detection_metrics(det: Detections, truth_box: np.ndarray, margin_px: float) -> dict:
    """Detection rate over frames where the UAV is visible, false detections, localisation error."""
    visible = np.isfinite(truth_box[:, 0])
    ok = det.found & correct(det.box_px, truth_box, margin_px)
    err = np.linalg.norm(box_centre(det.box_px[ok]) - box_centre(truth_box[ok]), axis=1)
    return {"frames": int(len(truth_box)), "frames_uav_visible": int(visible.sum()),
            "detected": int(ok.sum()), "missed": int((visible & ~ok).sum()),
            "false_positives": int((det.found & ~ok).sum()),
            "detection_rate": float(ok.sum() / max(visible.sum(), 1)),
            "false_positive_rate_per_frame": float((det.found & ~ok).sum() / max(len(truth_box), 1)),
            "localisation_error_px_p50": float(np.median(err)) if err.size else None,
            "localisation_error_px_p95": float(np.percentile(err, 95)) if err.size else None}


# --- beam prediction ------------------------------------------------------------------------------
def vision_features(box_px: np.ndarray) -> np.ndarray:
    """[u_centre, v_centre, width, height, found] per frame; a frame without a box gets
    (-1, -1, 0, 0, 0), a value no box has."""
    found = np.isfinite(box_px[:, 0])
    c = box_centre(np.nan_to_num(box_px, nan=0.0))
    wh = np.nan_to_num(box_px[:, 2:] - box_px[:, :2], nan=0.0)
    f = np.concatenate([c, wh, found[:, None].astype(float)], axis=1)
    f[~found, :2] = -1.0
    return f


def features(kind: str, gps_enu_m: np.ndarray, det_box: np.ndarray, truth_box: np.ndarray) -> np.ndarray:
    if kind == "position":
        return gps_enu_m
    if kind == "vision":
        return vision_features(det_box)
    if kind == "position+vision":
        return np.concatenate([gps_enu_m, vision_features(det_box)], axis=1)
    if kind == "truth_box":
        return vision_features(truth_box)
    if kind == "position+truth_box":
        return np.concatenate([gps_enu_m, vision_features(truth_box)], axis=1)
    raise KeyError(kind)


def top_k_hits(proba: np.ndarray, classes: np.ndarray, label: np.ndarray, k: int) -> np.ndarray:
    """True where ``label`` is among the ``k`` most probable classes (ties broken by class order)."""
    order = np.argsort(-proba, axis=1, kind="stable")[:, :k]
    return (classes[order] == label[:, None]).any(axis=1)


def beam_classifier(trees: int, seed: int):
    from sklearn.ensemble import RandomForestClassifier

    return RandomForestClassifier(n_estimators=trees, min_samples_leaf=1, random_state=seed, n_jobs=1)


def run_study(samples: list[WeatherSamples], train_flights: np.ndarray, test_flights: np.ndarray, *,
              seed: int = 0, margin_px: float = 4.0, trees: int = 300) -> dict:
    """The whole study on loaded samples: detectors, beam classifiers, tables (as numbers)."""
    train_masks = [np.isin(s.flight, train_flights) for s in samples]
    test_masks = [np.isin(s.flight, test_flights) for s in samples]
    detector = DifferenceDetector(seed=seed, margin_px=margin_px).fit(samples, train_masks)
    boxes = {"difference": [], "mog2": []}
    det_table = {d: {} for d in DETECTORS}
    for s, tr, te in zip(samples, train_masks, test_masks):
        # The trained detector runs on every frame (the beam classifier trains on its output for the
        # training flights); its scores are only reported on the test flights, where the baseline runs.
        d = detector.detect(s, tr | te)
        m = mog2_detect(s, te, warmup=s.rgb[np.flatnonzero(tr)[:: max(1, tr.sum() // 20)]])
        boxes["difference"].append(d.box_px)
        boxes["mog2"].append(m.box_px)
        for name, det in (("difference", d), ("mog2", m)):
            det_table[name][s.weather] = detection_metrics(Detections(det.box_px[te]), s.truth_box_px[te], margin_px)
    beam_table: dict[str, dict[str, dict]] = {}
    gain_loss: dict[str, dict[str, list]] = {}
    for kind in FEATURE_SETS:
        X = [features(kind, s.gps_enu_m, boxes["difference"][i], s.truth_box_px) for i, s in enumerate(samples)]
        clf = beam_classifier(trees, seed).fit(np.concatenate([x[m] for x, m in zip(X, train_masks)]),
                                               np.concatenate([s.best_beam[m] for s, m in zip(samples, train_masks)]))
        beam_table[kind], gain_loss[kind] = {}, {}
        for x, s, te in zip(X, samples, test_masks):
            proba = clf.predict_proba(x[te])
            row = {f"top{k}": float(top_k_hits(proba, clf.classes_, s.best_beam[te], k).mean()) for k in TOP_K}
            pred = clf.classes_[np.argmax(proba, axis=1)]
            g = s.beam_gain_db[te]
            loss = g[np.arange(len(pred)), s.best_beam[te]] - g[np.arange(len(pred)), pred]
            row["gain_loss_db_p50"] = float(np.median(loss))
            row["gain_loss_db_p95"] = float(np.percentile(loss, 95))
            row["samples"] = int(te.sum())
            beam_table[kind][s.weather] = row
            gain_loss[kind][s.weather] = loss.tolist()
    ref = next((s for s in samples if s.weather == "sunny"), samples[0])
    label_changes = {s.weather: float(np.mean(s.best_beam != ref.best_beam)) for s in samples
                     if s.weather != ref.weather and len(s.best_beam) == len(ref.best_beam)}
    return {"train_flights": train_flights.tolist(), "test_flights": test_flights.tolist(),
            "samples_per_weather": {s.weather: int(len(s.time_ns)) for s in samples},
            "distinct_best_beams": int(len(np.unique(np.concatenate([s.best_beam for s in samples])))),
            "label_change_vs": ref.weather, "label_change_fraction": label_changes,
            "detector_threshold": detector.threshold,
            "detector_noise_sigma": {w: float(v[1]) for w, v in detector.background.items()},
            "detection": det_table, "beam_prediction": beam_table, "gain_loss_db": gain_loss,
            "paper_top_k_percent": {w: dict(zip((f"top{k}" for k in TOP_K), v)) for w, v in PAPER_TOP_K.items()}}


# --- loading from the stores ----------------------------------------------------------------------
def num_flights(cfg) -> int:
    """The study UAV's flights: the legs of its waypoint trajectory."""
    p = next(q for q in cfg.platforms if q.name == cfg.beam_study.platform)
    return len(p.trajectory.waypoints_m) - 1


def flights_of(cfg, trajectory) -> tuple[np.ndarray, int]:
    """(passage times of the interior waypoints in ns, number of flights) of the study's UAV."""
    st = cfg.beam_study
    p = next(q for q in cfg.platforms if q.name == st.platform)
    pos = trajectory["position_m"].sel(platform=st.platform).values
    passages = waypoint_passage_times(trajectory["time"].values, pos, np.asarray(p.trajectory.waypoints_m),
                                      p.trajectory.waypoint_tolerance_m)
    return passages, num_flights(cfg)


def load_samples(cfg, weather: str, kpis, camera, gps, passages_ns: np.ndarray) -> WeatherSamples:
    """One weather's samples: ``kpis`` (Dataset), ``camera`` and ``gps`` (the sensor Datasets)."""
    st = cfg.beam_study
    link = np.flatnonzero((kpis["tx"].values == st.base_station) & (kpis["rx"].values == st.platform))
    if link.size != 1:
        raise ValueError(f"kpis of {weather}: no single link {st.base_station} -> {st.platform}")
    t = np.intersect1d(kpis["time"].values, camera["time"].values)
    if t.size == 0:
        raise ValueError(f"{weather}: the camera {st.base_station}/{st.camera} has no frame at a radio instant")
    k = kpis.sel(time=t).isel(link=int(link[0]))
    cam = camera.sel(time=t, actor=st.platform)
    box = cam["actor_visible_box_px"].sel(box_corner=list(BOX_CORNERS)).values.astype(float)
    box[cam["actor_pixel_count"].values <= 0] = np.nan
    # The latest valid GPS fix at or before each instant (a receiver reports what it has).
    g_t = gps["time"].values[gps["fix_valid"].values]
    g_xyz = gps["fix_enu_m"].values[gps["fix_valid"].values]
    j = np.searchsorted(g_t, t, side="right") - 1
    if (j < 0).any():
        raise ValueError(f"{weather}: no GPS fix before {int((j < 0).sum())} of the study's instants")
    return WeatherSamples(weather=weather, time_ns=t, flight=flight_of(t, passages_ns),
                          best_beam=k["best_beam"].values.astype(int), beam_gain_db=k["beam_gain_db"].values,
                          rgb=cam["rgb"].values, truth_box_px=box, gps_enu_m=g_xyz[j])


def study_problems(results: dict, num_flights: int) -> list[str]:
    """What is wrong with a study's results: a flight in both sets or in neither, a top-k row that
    does not grow with k, detection counts that do not add up. Empty when sound."""
    train, test = set(results["train_flights"]), set(results["test_flights"])
    problems = [f"flight {f} is in both the training and the test set" for f in sorted(train & test)]
    problems += [f"flight {f} is in neither set" for f in sorted(set(range(num_flights)) - train - test)]
    for kind, rows in results["beam_prediction"].items():
        for w, r in rows.items():
            tops = [r[f"top{k}"] for k in TOP_K]
            if not all(0.0 <= a <= b <= 1.0 for a, b in zip(tops, tops[1:])):
                problems.append(f"{kind} / {w}: top-k {tops} does not grow with k within 0..1")
    for name, rows in results["detection"].items():
        for w, m in rows.items():
            if m["detected"] + m["missed"] != m["frames_uav_visible"] or m["frames_uav_visible"] > m["frames"]:
                problems.append(f"detector {name} / {w}: detected + missed != frames with the UAV visible")
    return problems


# --- report ---------------------------------------------------------------------------------------
def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.2f} %"


def report_markdown(results: dict, scene: str) -> str:
    w = list(results["samples_per_weather"])
    bp, det = results["beam_prediction"], results["detection"]
    lines = [f"# Beam prediction study: scene `{scene}`", "",
             f"Flights: {len(results['train_flights']) + len(results['test_flights'])} "
             f"(training {results['train_flights']}, test {results['test_flights']}); samples per weather "
             + ", ".join(f"{k} {v}" for k, v in results["samples_per_weather"].items())
             + f"; {results['distinct_best_beams']} distinct best beams of the codebook.", "",
             "Best-beam labels that differ from " + results["label_change_vs"] + "'s: "
             + (", ".join(f"{k} {_pct(v)}" for k, v in results["label_change_fraction"].items()) or "–") + ".", "",
             "## Beam prediction on the test flights (top-k accuracy)", "",
             "| features | weather | top-1 | top-3 | top-5 | gain loss p50 / p95 (dB) |", "|---|---|---|---|---|---|"]
    for kind, rows in bp.items():
        for weather in w:
            r = rows[weather]
            lines.append(f"| {kind} | {weather} | {_pct(r['top1'])} | {_pct(r['top3'])} | {_pct(r['top5'])} | "
                         f"{r['gain_loss_db_p50']:.2f} / {r['gain_loss_db_p95']:.2f} |")
    lines += ["", "## Against the paper (position + vision, detector in the loop)", "",
              "| weather | top-1 (paper) | top-3 (paper) | top-5 (paper) |", "|---|---|---|---|"]
    for weather in w:
        r, p = bp["position+vision"][weather], PAPER_TOP_K.get(weather)
        if p is None:
            continue
        lines.append("| " + weather + " | " + " | ".join(
            f"{100 * r[f'top{k}']:.2f} % ({p[i]:.2f} %, {100 * r[f'top{k}'] - p[i]:+.2f} pp)"
            for i, k in enumerate(TOP_K)) + " |")
    lines += ["", "## UAV detection on the test flights", "",
              "| detector | weather | frames (UAV visible) | detected | missed | false positives | "
              "localisation error p50 / p95 (px) |", "|---|---|---|---|---|---|---|"]
    for name, rows in det.items():
        for weather in w:
            r = rows[weather]
            loc = "–" if r["localisation_error_px_p50"] is None else \
                f"{r['localisation_error_px_p50']:.1f} / {r['localisation_error_px_p95']:.1f}"
            lines.append(f"| {name} | {weather} | {r['frames']} ({r['frames_uav_visible']}) | {r['detected']} "
                         f"({_pct(r['detection_rate'])}) | {r['missed']} | {r['false_positives']} | {loc} |")
    return "\n".join(lines) + "\n"


def figure(results: dict, title: str = ""):
    """Top-k per feature set and weather against the paper, and the CDF of the predicted beam's gain
    loss against the best beam."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    weathers = list(results["samples_per_weather"])
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.6))
    kinds = list(results["beam_prediction"])
    width = 0.8 / (len(kinds) + 1)
    x = np.arange(len(weathers))
    for i, kind in enumerate(kinds):
        a.bar(x + i * width, [100 * results["beam_prediction"][kind][w]["top1"] for w in weathers], width, label=kind)
    a.bar(x + len(kinds) * width, [PAPER_TOP_K.get(w, (np.nan,))[0] for w in weathers], width, label="paper",
          color="0.3", hatch="//")
    a.set_xticks(x + width * len(kinds) / 2, weathers)
    a.set_ylabel("top-1 accuracy (%)")
    a.set_ylim(0, 105)
    a.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.1))
    a.set_title("top-1 on the test flights")
    for kind, style in (("position", ":"), ("vision", "--"), ("position+vision", "-")):
        for w, colour in zip(weathers, ("tab:orange", "tab:blue", "tab:purple")):
            loss = np.sort(results["gain_loss_db"][kind][w])
            b.step(loss, np.arange(1, len(loss) + 1) / len(loss), style, color=colour, label=f"{kind}, {w}")
    b.set_xlabel("beam gain loss of the predicted beam (dB)")
    b.set_ylabel("CDF")
    b.set_xlim(-0.5, 15)
    b.legend(fontsize=6, loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
