"""Replay never invents motion (issue 16): property tests over random recordings with jitter,
repeated stamps, gaps and shuffled order, the stamp rules' refusals, and the dynamic-limits policy."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from simart_pipeline.config import DEFAULT_LIMITS, DynamicLimits
from simart_pipeline.mobility import replay
from simart_pipeline.mobility.errors import ReplayError

CAR = DynamicLimits(**DEFAULT_LIMITS["ground_vehicle"])


@st.composite
def recordings(draw):
    """A random walk in 3D with random intervals, some jittered into bursts microseconds apart,
    some stamps repeated with the same pose, some gaps, in shuffled order."""
    n = draw(st.integers(3, 40))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    base_dt_s = draw(st.sampled_from([0.005, 0.02, 0.1, 0.5]))
    dt_s = base_dt_s * rng.uniform(0.5, 1.5, n - 1)
    burst = rng.random(n - 1) < draw(st.floats(0, 0.4))
    dt_s[burst] = rng.uniform(1e-6, 1e-4, burst.sum())  # arrival bursts, tens of microseconds apart
    gap = rng.random(n - 1) < 0.1
    dt_s[gap] *= 8.0
    t_ns = np.concatenate([[0], np.cumsum(np.round(dt_s * 1e9).astype(np.int64))])
    step_m = rng.normal(0.0, draw(st.sampled_from([0.01, 1.0, 30.0])), (n, 3))
    pos = np.cumsum(step_m, axis=0) + rng.uniform(-1e4, 1e4, 3)
    rec = {"time_ns": t_ns, "position_m": pos}
    dup = rng.random(n) < 0.15  # the same message recorded twice
    rec = {k: np.concatenate([v, v[dup]]) for k, v in rec.items()}
    order = rng.permutation(len(rec["time_ns"]))
    return {k: v[order] for k, v in rec.items()}


def _on_segment(p, a, b) -> float:
    """Distance from p to the segment [a, b]."""
    ab = b - a
    s = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + s * ab)))


@settings(max_examples=150, deadline=None, derandomize=True)
@given(rec=recordings(), fractions=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=20))
def test_replay_stays_between_recorded_neighbours_and_never_outruns_them(rec, fractions):
    raw_t = rec["time_ns"]
    clean = replay.clean(rec, "random.csv", max_gap_s=None)
    t, p = clean["time_ns"], clean["position_m"]
    assert np.all(np.diff(t) > 0)
    # every cleaned pose (a merged burst is the mean of its poses) lies in the bounding box of the raw
    # poses recorded within one median interval of its stamp
    median = np.median(np.diff(np.unique(raw_t)))
    for ti, pi in zip(t, p):
        near = rec["position_m"][np.abs(raw_t - ti) <= median]
        assert np.all(pi >= near.min(0) - 1e-9) and np.all(pi <= near.max(0) + 1e-9)
    q = np.round(t[0] + np.asarray(fractions) * (t[-1] - t[0])).astype(np.int64)
    out = replay.resample(clean, q)
    seg = np.clip(np.searchsorted(t, q, side="right") - 1, 0, len(t) - 2)
    speed_seg = np.linalg.norm(np.diff(p, axis=0), axis=1) / (np.diff(t) / 1e9)
    scale = 1.0 + np.abs(p).max()
    for k, i in enumerate(seg):
        # inside the convex hull (the segment) of the two recorded neighbours
        assert _on_segment(out["position_m"][k], p[i], p[i + 1]) <= 1e-9 * scale
        # no faster than the displacement per time of the segments around it
        bound = speed_seg[max(i - 1, 0):i + 2].max()
        assert np.linalg.norm(out["velocity_mps"][k]) <= bound * (1 + 1e-9) + 1e-12
    assert np.all(np.isfinite(out["acceleration_mps2"]))


def test_shuffled_recording_replays_as_the_sorted_one():
    rng = np.random.default_rng(3)
    t = np.arange(50, dtype=np.int64) * 20_000_000
    pos = np.cumsum(rng.normal(0, 0.1, (50, 3)), axis=0)
    order = rng.permutation(50)
    q = np.arange(0, 980_000_000, 7_000_000, dtype=np.int64)
    a = replay.resample(replay.clean({"time_ns": t, "position_m": pos}, "a"), q)
    b = replay.resample(replay.clean({"time_ns": t[order], "position_m": pos[order]}, "b"), q)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def _robot_in_a_box(jitter: bool):
    """A ground robot circling inside 5 m x 3 m at 1 m/s, poses at 50 Hz; with ``jitter``, record
    times as a bag stores them: every fifth message arrives 30 microseconds after the one before."""
    t_s = np.arange(0, 20, 0.02)
    pos = np.stack([2.5 + 2.0 * np.cos(t_s / 2.0), 1.5 + 1.0 * np.sin(t_s / 2.0), np.zeros_like(t_s)], -1)
    t_ns = np.round(t_s * 1e9).astype(np.int64)
    if jitter:
        t_ns[5::5] = t_ns[4:-1:5] + 30_000
    return {"time_ns": t_ns, "position_m": pos}


def test_jittered_record_times_stay_in_the_box_at_the_robots_speed():
    """The issue's scene: the cubic spline took this robot 1.2 km away at 5.6e4 m/s."""
    rec = replay.clean(_robot_in_a_box(jitter=True), "robot.bag: topic /odom", max_gap_s=1.0,
                       max_speed_mps=CAR.max_speed_mps)
    assert replay.check_limits(rec, 0.0, CAR, "robot") == []
    q = np.arange(0, 20_000_000_000, 1_000_000, dtype=np.int64)  # 1 kHz
    out = replay.resample(rec, q)
    x, y = out["position_m"][:, 0], out["position_m"][:, 1]
    assert x.min() >= 0 and x.max() <= 5 and y.min() >= 0 and y.max() <= 3
    assert np.linalg.norm(out["velocity_mps"], axis=1).max() < 1.5  # truth: 1.12 m/s at most


def test_repeated_stamps_with_another_pose_are_refused_by_name():
    rec = _robot_in_a_box(jitter=False)
    rec["time_ns"][10] = rec["time_ns"][9]
    with pytest.raises(ReplayError, match=r"robot\.bag: topic /odom: 1 recorded poses repeat the stamp .* "
                                          r"try stamp: record"):
        replay.clean(rec, "robot.bag: topic /odom", repeated_hint="; try stamp: record")
    # the same message recorded twice is kept once
    rec = _robot_in_a_box(jitter=False)
    twice = {k: np.insert(v, 10, v[9], axis=0) for k, v in rec.items()}
    got = replay.clean(twice, "robot.bag")
    for k in rec:
        np.testing.assert_array_equal(got[k], rec[k])


def test_a_topic_interleaving_two_robots_is_refused_and_one_glitch_fails_the_limits():
    a = _robot_in_a_box(jitter=False)
    b = {"time_ns": a["time_ns"] + 10_000_000, "position_m": a["position_m"] + [20.0, 0.0, 0.0]}
    both = {k: np.concatenate([a[k], b[k]]) for k in a}
    with pytest.raises(ReplayError, match=r"two\.bag: topic /pose: the poses jump to another track and back "
                                          r"\d+ times .*interleave two sources"):
        replay.clean(both, "two.bag: topic /pose", max_speed_mps=CAR.max_speed_mps)
    glitch = _robot_in_a_box(jitter=False)
    glitch["position_m"][300] += [20.0, 0.0, 0.0]
    rec = replay.clean(glitch, "glitch.bag", max_speed_mps=CAR.max_speed_mps)  # one return: no interleave
    with pytest.raises(ReplayError, match=r"glitch: replayed speed reaches .* above limits\.max_speed_mps 13\.9"):
        replay.check_limits(rec, 0.0, CAR, "glitch")


def test_gaps_beyond_max_gap_are_refused_with_the_gap_named():
    rec = _robot_in_a_box(jitter=False)
    keep = (rec["time_ns"] < 5e9) | (rec["time_ns"] > 7.5e9)
    rec = {k: v[keep] for k, v in rec.items()}
    with pytest.raises(ReplayError, match=r"gap\.csv: 1 gap\(s\) .* exceed trajectory\.max_gap_s = 1 s, "
                                          r"the longest 2\.540 s from 4\.980000 s"):
        replay.clean(rec, "gap.csv", max_gap_s=1.0)
    got = replay.clean(rec, "gap.csv", max_gap_s=3.0)  # across it: a straight line
    mid = replay.resample(got, np.array([6_000_000_000]))["position_m"][0]
    i = int(np.searchsorted(got["time_ns"], 6e9)) - 1
    assert _on_segment(mid, got["position_m"][i], got["position_m"][i + 1]) < 1e-12


def test_dynamic_limits_policy_refuse_warn_accept(caplog):
    t = np.arange(0, 50, dtype=np.int64) * 100_000_000
    fast = {"time_ns": t, "position_m": np.stack([30.0 * t / 1e9, np.zeros(50), np.zeros(50)], -1)}  # 108 km/h
    with pytest.raises(ReplayError, match=r"car0: replayed speed reaches 30 m/s .* above limits\.max_speed_mps "
                                          r"13\.9 m/s .*dynamic_limits: warn or accept"):
        replay.check_limits(fast, 0.0, CAR, "car0")
    with caplog.at_level(logging.WARNING, logger="simart_pipeline.mobility.replay"):
        problems = replay.check_limits(fast, 0.0, CAR, "car0", policy="warn")
    assert len(problems) == 1 and problems[0] in caplog.text
    caplog.clear()
    assert replay.check_limits(fast, 0.0, CAR, "car0", policy="accept") == problems and not caplog.text
    # a stop from 10 m/s within 0.2 s (50 m/s2) is refused on acceleration, not speed
    v = np.where(t < 2.5e9, 10.0, 0.0)
    stop = {"time_ns": t, "position_m": np.stack([np.cumsum(v) * 0.1, np.zeros(50), np.zeros(50)], -1)}
    with pytest.raises(ReplayError, match=r"acceleration \(over 0\.5 s\) reaches .*limits\.max_acceleration_mps2 3 m/s2"):
        replay.check_limits(stop, 0.0, CAR, "car0")


def test_validate_reports_two_sources_and_repeated_stamps_before_any_work(tiny_scene):
    from simart_pipeline.validation import scene_problems

    path = tiny_scene / "scene.yaml"
    raw = yaml.safe_load(path.read_text())
    raw["platforms"][0]["trajectory"] = {"kind": "replay", "path": "car.csv"}
    path.write_text(yaml.safe_dump(raw))
    t = np.arange(0, 40, dtype=np.int64) * 50_000_000
    x = [float(v) for v in -30.0 + 2.0 * t / 1e9]
    lines = [f"{ti},{xi!r},-18.0,1.5" for ti, xi in zip(t, x)]
    (tiny_scene / "car.csv").write_text("time_ns,x_m,y_m,z_m\n" + "\n".join(lines) + "\n")
    assert scene_problems(tiny_scene)[1] == []
    two = lines + [f"{ti + 25_000_000},{xi + 20.0!r},-18.0,1.5" for ti, xi in zip(t, x)]
    (tiny_scene / "car.csv").write_text("time_ns,x_m,y_m,z_m\n" + "\n".join(two) + "\n")
    problems = scene_problems(tiny_scene)[1]
    assert len(problems) == 1 and problems[0].startswith(f"{path}: platforms.0.trajectory: ")
    assert "car.csv: the poses jump to another track and back" in problems[0]
    lines[5] = f"{t[4]},{x[5]!r},-18.0,1.5"
    (tiny_scene / "car.csv").write_text("time_ns,x_m,y_m,z_m\n" + "\n".join(lines) + "\n")
    problems = scene_problems(tiny_scene)[1]
    assert len(problems) == 1 and "repeat the stamp of the one before with other values" in problems[0]
