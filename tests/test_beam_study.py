"""The beam-prediction study (docs/beam-study.md): flights, split, detectors, top-k, and the asset
on a small study scene end to end."""

import json
from pathlib import Path

import numpy as np
import pytest

from simart_pipeline.study import beam_prediction as bp

HERE = Path(__file__).parent


def test_passage_times_of_a_constant_speed_zigzag():
    # Three legs of 20 m at 2 m/s through exact corners: passages at 10 s and 20 s.
    wp = np.array([[0, 0, 5], [20, 0, 5], [20, 20, 5], [0, 20, 5]], float)
    t = np.arange(0, 30.01, 0.01)
    pos = np.empty((t.size, 3))
    for k in range(3):
        sel = (t >= 10 * k) & (t <= 10 * (k + 1))
        pos[sel] = wp[k] + (wp[k + 1] - wp[k]) * ((t[sel] - 10 * k) / 10)[:, None]
    t_ns = np.round(t * 1e9).astype(np.int64)
    passages = bp.waypoint_passage_times(t_ns, pos, wp, tolerance_m=1.0)
    assert np.allclose(passages / 1e9, [10.0, 20.0], atol=0.011)
    assert np.array_equal(bp.flight_of(np.array([0, 9_990_000_000, 10_010_000_000, 29_000_000_000]), passages),
                          [0, 0, 1, 2])


def test_passage_times_take_the_passage_in_order_when_a_path_revisits_a_waypoint():
    # Out and back along a line: waypoint 1 (x = 10) is passed at t = 10 s, waypoint 2 (x = 0) at
    # 20 s, though x = 0 is also where the path started.
    wp = np.array([[0, 0, 5], [10, 0, 5], [0, 0, 5], [10, 0, 5]], float)
    t = np.arange(0, 30.01, 0.01)
    x = np.interp(t, [0, 10, 20, 30], [0, 10, 0, 10])
    pos = np.stack([x, 0 * x, 5 + 0 * x], axis=1)
    passages = bp.waypoint_passage_times(np.round(t * 1e9).astype(np.int64), pos, wp, tolerance_m=1.0)
    assert np.allclose(passages / 1e9, [10.0, 20.0], atol=0.011)


@pytest.mark.parametrize("n,fraction,seed", [(24, 0.25, 0), (5, 0.5, 3), (2, 0.9, 1), (7, 0.01, 2)])
def test_split_is_by_flight_disjoint_complete_and_seeded(n, fraction, seed):
    train, test = bp.split_flights(n, fraction, seed)
    assert len(train) >= 1 and len(test) >= 1
    assert not set(train) & set(test)
    assert sorted([*train, *test]) == list(range(n))
    again = bp.split_flights(n, fraction, seed)
    assert np.array_equal(train, again[0]) and np.array_equal(test, again[1])
    with pytest.raises(ValueError, match="at least two flights"):
        bp.split_flights(1, fraction, seed)


def test_top_k_against_a_sorted_reference():
    rng = np.random.default_rng(5)
    proba = rng.random((200, 9))
    classes = np.array([3, 5, 7, 11, 13, 17, 19, 23, 29])
    label = rng.choice(classes, 200)
    for k in (1, 3, 5, 9):
        ref = np.array([lab in [classes[j] for j in sorted(range(9), key=lambda j: -p[j])[:k]]
                        for p, lab in zip(proba, label)])
        assert np.array_equal(bp.top_k_hits(proba, classes, label, k), ref)
    assert bp.top_k_hits(proba, classes, label, 9).all()


def _moving_square_frames(n=120, size=3, night=False, seed=0):
    """A fixed camera's frames: a textured static background with sensor noise, and a small dark
    square that moves along a known path (its true box), four flights of 30 frames."""
    rng = np.random.default_rng(seed)
    h, w = 90, 120
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([60 + 40 * np.sin(xx / 9.0), 80 + 30 * np.cos(yy / 7.0), 100 + 0 * xx], -1)
    if night:
        base = base * 0.25
    frames, boxes = [], []
    for i in range(n):
        f = base + rng.normal(0, 3.0 if night else 1.5, base.shape)
        u = 10 + (i % 30) * 3.0
        v = 15 + 40 * (i // 30) / 3 + 10 * np.sin(i / 5)
        u0, v0 = int(u), int(v)
        f[v0:v0 + size, u0:u0 + size] = (70, 70, 60) if night else (20, 20, 25)  # lit at night
        if i % 3 == 0:  # a distractor: a bright streak somewhere (rain, a glint)
            r, c = rng.integers(0, h - 8), rng.integers(0, w - 2)
            f[r:r + 8, c:c + 2] = 230
        frames.append(np.clip(f, 0, 255).astype(np.uint8))
        boxes.append((u0, v0, u0 + size, v0 + size))
    return np.stack(frames), np.asarray(boxes, float)


def _samples(weather, frames, boxes):
    n = len(frames)
    return bp.WeatherSamples(weather=weather, time_ns=np.arange(n, dtype=np.int64) * 500_000_000,
                             flight=np.arange(n) // 30, best_beam=np.zeros(n, int),
                             beam_gain_db=np.zeros((n, 1)), rgb=frames, truth_box_px=boxes,
                             gps_enu_m=np.zeros((n, 3)))


def test_detectors_find_a_moving_square_where_it_is():
    samples = [_samples("sunny", *_moving_square_frames()),
               _samples("night", *_moving_square_frames(night=True, seed=1))]
    train = [s.flight < 3 for s in samples]
    test = [s.flight == 3 for s in samples]
    det = bp.DifferenceDetector(seed=0, margin_px=2.0).fit(samples, train)
    for s, te in zip(samples, test):
        found = det.detect(s, te)
        m = bp.detection_metrics(bp.Detections(found.box_px[te]), s.truth_box_px[te], 2.0)
        assert m["frames_uav_visible"] == 30
        assert m["detection_rate"] >= 0.9, (s.weather, m)
        assert m["false_positives"] <= 1, (s.weather, m)
        assert m["localisation_error_px_p95"] <= 1.5, (s.weather, m)
    # The baseline needs no training: it finds the square in every sunny frame without a distractor,
    # and takes the larger streak for it where one appears (why the trained scorer exists).
    s = samples[0]
    mog = bp.mog2_detect(s, test[0], warmup=s.rgb[train[0]][::5])
    hit = bp.correct(mog.box_px, s.truth_box_px, 2.0)
    clean = test[0] & (np.arange(len(hit)) % 3 != 0)
    assert hit[clean].all()
    assert not hit[test[0] & ~clean].any()


def test_detection_metrics_count_misses_and_false_positives():
    truth = np.array([[10, 10, 14, 14], [20, 20, 22, 22], [np.nan] * 4, [30, 30, 34, 34]], float)
    det = np.array([[11, 11, 13, 13], [50, 50, 52, 52], [5, 5, 7, 7], [np.nan] * 4], float)
    m = bp.detection_metrics(bp.Detections(det), truth, margin_px=2.0)
    assert (m["frames"], m["frames_uav_visible"], m["detected"], m["missed"], m["false_positives"]) == (4, 3, 1, 2, 2)
    assert m["localisation_error_px_p50"] == pytest.approx(0.0)


def test_vision_features_mark_frames_without_a_box():
    f = bp.vision_features(np.array([[10, 20, 14, 30], [np.nan] * 4], float))
    assert np.array_equal(f, [[12, 25, 4, 10, 1], [-1, -1, 0, 0, 0]])


# --- the asset on a small study scene -------------------------------------------------------------
@pytest.fixture(scope="module")
def beam_tiny_run(tmp_path_factory):
    """tests/scenes/beam_tiny materialised once through ``simart run``'s code path."""
    import dagster as dg

    from conftest import TESTS

    from simart_pipeline.cli import materialize_scene

    data = tmp_path_factory.mktemp("beam_tiny")
    instance = dg.DagsterInstance.ephemeral()
    lines = []
    materialize_scene(TESTS / "scenes" / "beam_tiny", data, instance=instance, progress=lines.append)
    return data, instance, lines


def test_beam_prediction_asset_splits_by_flight_and_reports_every_row(beam_tiny_run):
    import xarray as xr

    from conftest import TESTS

    from simart_pipeline import stores
    from simart_pipeline.config import load_scene_config

    data, instance, lines = beam_tiny_run
    assert any(line.startswith("[") and "beam_prediction (beam_tiny): computing" in line for line in lines)
    out = stores.store_path(data, "beam_prediction", "beam_tiny", suffix="")
    results = json.loads((out / "results.json").read_text())
    cfg = load_scene_config(TESTS / "scenes" / "beam_tiny")
    flights = len(cfg.platforms[0].trajectory.waypoints_m) - 1
    train, test = set(results["train_flights"]), set(results["test_flights"])
    assert train and test and not train & test and train | test == set(range(flights))
    assert len(test) == round(cfg.beam_study.test_fraction * flights)
    # Labels: the best beam of the bs0 -> uav0 link at the camera's instants, from each weather's kpis.
    weathers = list(cfg.weathers)
    assert set(results["samples_per_weather"]) == set(weathers)
    beams = set()
    for w in weathers:
        k = xr.open_zarr(stores.store_path(data, "kpis", "beam_tiny", w))
        link = int(np.flatnonzero((k["tx"].values == "bs0") & (k["rx"].values == "uav0"))[0])
        cam = xr.open_datatree(stores.store_path(data, "sensor_frames", "beam_tiny", w), engine="zarr")["bs0/cam"]
        t = np.intersect1d(k["time"].values, cam["time"].values)
        assert results["samples_per_weather"][w] == len(t)
        beams |= set(k["best_beam"].isel(link=link).sel(time=t).values.tolist())
    assert results["distinct_best_beams"] == len(beams)
    # Every row is there, top-k grows with k, and the detector finds the UAV in the test frames of
    # every weather (at night by its lights) without false detections.
    for kind in bp.FEATURE_SETS:
        for w in weathers:
            row = results["beam_prediction"][kind][w]
            assert 0.0 <= row["top1"] <= row["top3"] <= row["top5"] <= 1.0
    for w in weathers:
        m = results["detection"]["difference"][w]
        assert m["frames"] == results["beam_prediction"]["position"][w]["samples"]
        assert m["detected"] + m["missed"] == m["frames_uav_visible"] > 0
        assert m["detection_rate"] >= 0.8, (w, m)
        assert m["false_positives"] <= 0.1 * m["frames"], (w, m)
        assert m["localisation_error_px_p95"] <= 2.0, (w, m)
    report = (out / "report.md").read_text()
    for w in weathers:
        assert f"| position+vision | {w} |" in report and f"| difference | {w} |" in report
    assert (out / "beam_prediction.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The Dagster UI gets the table, the picture and the split.
    import dagster as dg

    event = instance.get_latest_materialization_event(dg.AssetKey("beam_prediction"))
    meta = event.asset_materialization.metadata
    assert "data:image/png;base64," in meta["picture"].value
    assert "| position+vision |" in meta["report"].value
    assert meta["test_flights"].value == str(sorted(test))
    # Its asset check ran with it and passed; the same check finds a leaked flight.
    check = instance.event_log_storage.get_latest_asset_check_execution_by_key(
        [dg.AssetCheckKey(dg.AssetKey("beam_prediction"), "beam_study_sound")])
    assert next(iter(check.values())).status.value == "SUCCEEDED"
    leaked = dict(results, test_flights=results["test_flights"] + results["train_flights"][:1])
    assert bp.study_problems(results, flights) == []
    assert bp.study_problems(leaked, flights) == [f"flight {results['train_flights'][0]} is in both the "
                                                  "training and the test set"]
