"""Mobility: trajectories from waypoints under dynamic limits, road following, attitude."""

from __future__ import annotations

import shutil

import networkx as nx
import numpy as np
import pytest
import shapely
import yaml
from scipy.spatial.transform import Rotation
from shapely.geometry import LineString

from conftest import SHARED_DATA, TESTS

from simart_pipeline.config import DEFAULT_LIMITS, ConfigError, SceneConfig, load_scene_config
from simart_pipeline.mobility import roads
from simart_pipeline.mobility import path as geo
from simart_pipeline.mobility.trajectory import (build_trajectory, check_clear_of_buildings, plan_platform,
                                                 waypoint_path)
from simart_pipeline.scene import source
from simart_pipeline.scene.geometry import Feature, SourceGeometry
from simart_pipeline.vocabulary import STANDARD_GRAVITY_MPS2
from simart_pipeline.validation import scene_problems

ORIGIN = {"latitude_deg": 48.1372, "longitude_deg": 11.5755, "altitude_m": 519.0}
# A zigzag with a gentle bend, a right angle, a hairpin and a return along the same line.
ZIGZAG = [(0, 0, 10), (60, 0, 12), (90, 20, 12), (90, 60, 15), (50, 62, 14), (80, 64, 14), (20, 64, 10)]


def scene(kind="uav", waypoints=ZIGZAG, speed=8.0, limits=None, source=None, duration=5.0, **traj):
    plat = {"name": "p0", "kind": kind, "trajectory": {"waypoints_m": [list(w) for w in waypoints],
                                                       "speed_mps": speed, **traj}}
    if limits is not None:
        plat["limits"] = limits
    return SceneConfig.model_validate({
        "name": "t", "source": source or {"kind": "procedural"}, "origin": ORIGIN,
        "base_stations": [{"name": "bs0", "position_m": [0.0, 0.0, 30.0]}],
        "platforms": [plat], "clock": {"duration_s": duration}})


def dense(plan, dt=1e-3):
    t = np.arange(plan.start_s - 0.5, plan.end_s + 0.5, dt)
    return t, plan.evaluate(t)


def norm(x):
    return np.linalg.norm(x, axis=-1)


CASES = {
    "uav": dict(kind="uav", speed=12.0),
    "uav_tight": dict(kind="uav", speed=15.0, waypoint_tolerance_m=4.0,
                      limits={"max_acceleration_mps2": 2.0, "max_jerk_mps3": 1.0}),
    "car": dict(kind="ground_vehicle", speed=13.0, follow_roads=False, waypoints=[(x, y, 1.5) for x, y, _ in ZIGZAG]),
    "pedestrian": dict(kind="pedestrian", speed=1.4, waypoint_tolerance_m=0.5,
                       waypoints=[(x / 10, y / 10, 1.2) for x, y, _ in ZIGZAG]),
    "stops": dict(kind="pedestrian", speed=2.5, waypoint_tolerance_m=0.0,
                  waypoints=[(x / 10, y / 10, 1.2) for x, y, _ in ZIGZAG]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_limits_are_never_exceeded(case):
    cfg = scene(**CASES[case])
    p = cfg.platforms[0]
    lim = p.limits
    plan = plan_platform(p)
    t, st = dense(plan, 5e-4)
    dt = t[1] - t[0]
    v, a, j = st["velocity_mps"], st["acceleration_mps2"], st["jerk_mps3"]
    # The stored derivatives are the derivatives (central differences, away from jerk switches).
    fd_v = (st["position_m"][2:] - st["position_m"][:-2]) / (2 * dt)
    fd_a = (v[2:] - v[:-2]) / (2 * dt)
    assert np.percentile(norm(fd_v - v[1:-1]), 99) < 1e-5
    assert np.percentile(norm(fd_a - a[1:-1]), 99) < 1e-4
    # Limits, on the values and on the mean-value bounds |dx/dt| <= sup |x'| between samples.
    eps = 1 + 1e-9
    speed = min(p.trajectory.speed_mps, lim.max_speed_mps)
    assert norm(v).max() <= speed * eps and norm(np.diff(st["position_m"], axis=0)).max() / dt <= speed * eps
    assert norm(a).max() <= lim.max_acceleration_mps2 * eps
    assert norm(np.diff(v, axis=0)).max() / dt <= lim.max_acceleration_mps2 * eps
    assert norm(j).max() <= lim.max_jerk_mps3 * eps
    assert norm(np.diff(a, axis=0)).max() / dt <= lim.max_jerk_mps3 * eps
    moving = norm(v) > 1e-6
    u = v[moving] / norm(v[moving])[:, None]
    a_t = np.einsum("ij,ij->i", a[moving], u)
    a_n = norm(a[moving] - a_t[:, None] * u)
    assert np.abs(a_t).max() <= lim.max_tangential_acceleration_mps2 * eps
    assert a_n.max() <= lim.max_lateral_acceleration_mps2 * eps
    ratios = plan.limit_ratios()
    assert max(ratios.values()) <= 1.0 and ratios["jerk"] > 0.99  # within, and not needlessly slow
    # The analytic check samples every piece of constant jerk: it sees at least what dense sampling sees.
    assert norm(j).max() / lim.max_jerk_mps3 <= ratios["jerk"] + 1e-12
    assert norm(a).max() / lim.max_acceleration_mps2 <= ratios["acceleration"] + 1e-12


@pytest.mark.parametrize("case", ["uav", "pedestrian", "stops"])
def test_waypoints_are_reached_within_tolerance_from_rest_to_rest(case):
    cfg = scene(**CASES[case])
    p = cfg.platforms[0]
    wp = np.asarray(p.trajectory.waypoints_m)
    tol = p.trajectory.waypoint_tolerance_m
    plan = plan_platform(p)
    t, st = dense(plan, 2e-4)
    pos, v = st["position_m"], st["velocity_mps"]
    # Closest sample to each waypoint: within the tolerance, up to half a sample step of travel.
    slack = norm(v).max() * 1e-4
    for k, w in enumerate(wp):
        d = norm(pos - w).min()
        assert d <= (tol if 0 < k < len(wp) - 1 else 0.0) + slack, (k, d)
    # Each corner's deviation is the tolerance, or less where a short segment limits the blend.
    dev = plan.path.deviation_m[~plan.path.stop]
    assert (dev <= tol * (1 + 1e-12)).all() and (tol == 0 or np.median(dev) == pytest.approx(tol, rel=1e-9))
    # At rest at the ends (before, at and after), standing on the first and last waypoint.
    for sel, end in ((t <= plan.start_s, wp[0]), (t >= plan.end_s, wp[-1])):
        assert sel.sum() > 100
        np.testing.assert_allclose(pos[sel], np.broadcast_to(end, pos[sel].shape), atol=1e-9)
        assert np.abs(v[sel]).max() == 0 and np.abs(st["acceleration_mps2"][sel]).max() == 0
    if tol == 0:  # stops at every waypoint, exactly on it
        for w in wp[1:-1]:
            i = np.argmin(norm(pos - w))
            assert norm(pos[i] - w) < 1e-9 and norm(v[i]) < 1e-9


def test_slows_down_in_turns_and_more_for_sharper_or_tighter_ones():
    def corner_speed(turn_deg, tol):
        c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
        cfg = scene(waypoints=[(0, 0, 20), (100, 0, 20), (100 + 100 * c, 100 * s, 20)], speed=15.0,
                    waypoint_tolerance_m=tol)
        plan = plan_platform(cfg.platforms[0])
        t, st = dense(plan, 1e-3)
        i = np.argmin(norm(st["position_m"] - [100, 0, 20]))
        return norm(st["velocity_mps"][i]), norm(st["velocity_mps"]).max()

    v30, top = corner_speed(30, 2.0)
    v90, _ = corner_speed(90, 2.0)
    v90_wide, _ = corner_speed(90, 8.0)
    assert v90 < v30 < top and v90 < v90_wide < top
    assert top == pytest.approx(15.0, rel=1e-6)  # cruises at speed_mps on the straights


def test_uniform_time_scaling_divides_speed_acceleration_and_jerk():
    plan = plan_platform(scene().platforms[0])
    before = plan.limit_ratios()
    end = plan.motion_duration_s
    plan.time_scaling = 2.0
    after = plan.limit_ratios()
    assert after["speed"] == pytest.approx(before["speed"] / 2, rel=1e-12)
    assert after["acceleration"] == pytest.approx(before["acceleration"] / 4, rel=1e-12)
    assert after["jerk"] == pytest.approx(before["jerk"] / 8, rel=1e-12)
    assert plan.motion_duration_s == pytest.approx(2 * end, rel=1e-12)


@pytest.mark.parametrize("case", ["uav", "car", "stops"])
def test_angular_velocity_is_the_derivative_of_the_orientation(case):
    plan = plan_platform(scene(**CASES[case]).platforms[0])
    dt = 1e-3
    t = np.arange(plan.start_s, plan.end_s, dt)
    st = plan.evaluate(t)
    rot = Rotation.from_quat(st["orientation_xyzw"])
    w = st["angular_velocity_radps"]
    # R_i^T R_{i+1} = exp(mean body rate * dt): compare away from the instants where the jerk
    # switches (the quadrotor's body rate steps there).
    fd = (rot[:-1].inv() * rot[1:]).as_rotvec() / dt
    bounds = plan.start_s + (plan.seg_t0 * plan.time_scaling)
    near = np.zeros(len(fd), bool)
    k = np.searchsorted(t, bounds)
    for off in (-2, -1, 0, 1):
        near[np.clip(k + off, 0, len(fd) - 1)] = True
    err = norm(fd - (w[1:] + w[:-1]) / 2)[~near]
    assert err.max() < 1e-5 * max(1.0, np.abs(w).max()), err.max()
    assert np.abs(w).max() > 0.05  # it does turn
    # Integrating the body rate over the whole motion returns the final attitude (midpoint rule on
    # a grid that holds every segment boundary, so no step straddles a rate step).
    grid = np.unique(np.concatenate([np.arange(plan.start_s, plan.end_s, 2e-3), bounds, [plan.end_s]]))
    steps = Rotation.from_rotvec(plan.evaluate((grid[1:] + grid[:-1]) / 2)["angular_velocity_radps"]
                                 * np.diff(grid)[:, None])
    while len(steps) > 1:  # ordered pairwise products: R0 R1 R2 ... in log2(n) vectorised rounds
        if len(steps) % 2:
            steps = Rotation.concatenate([steps, Rotation.identity(1)])
        steps = steps[0::2] * steps[1::2]
    start, end = (Rotation.from_quat(plan.evaluate([x])["orientation_xyzw"]) for x in (grid[0], grid[-1]))
    assert ((start * steps).inv() * end).magnitude()[0] < 1e-5
    # Quaternion signs never jump between neighbouring samples.
    q = st["orientation_xyzw"]
    assert (np.einsum("ij,ij->i", q[1:], q[:-1]) > 0).all()


def test_uav_attitude_is_the_thrust_direction_with_heading_along_velocity():
    plan = plan_platform(scene(**CASES["uav"]).platforms[0])
    t, st = dense(plan, 1e-2)
    rot = Rotation.from_quat(st["orientation_xyzw"])
    body_z = rot.apply([0.0, 0.0, 1.0])
    thrust = st["acceleration_mps2"] + [0.0, 0.0, STANDARD_GRAVITY_MPS2]
    np.testing.assert_allclose(body_z, thrust / norm(thrust)[:, None], atol=1e-12)
    assert np.degrees(np.arccos(body_z[:, 2])).max() > 5  # it does tilt
    vh = st["velocity_mps"][:, :2]
    fast = norm(vh) > 0.5
    x_h = rot.apply([1.0, 0.0, 0.0])[fast, :2]
    cosang = np.einsum("ij,ij->i", x_h / norm(x_h)[:, None], vh[fast] / norm(vh[fast])[:, None])
    assert cosang.min() > 1 - 1e-9
    # Ground platforms stay level.
    lvl = plan_platform(scene(**CASES["car"]).platforms[0]).evaluate(t)
    np.testing.assert_allclose(Rotation.from_quat(lvl["orientation_xyzw"]).apply([0, 0, 1.0]),
                               np.tile([0, 0, 1.0], (len(t), 1)), atol=1e-12)


def test_turns_in_place_at_a_reversal_within_the_yaw_limits():
    cfg = scene(kind="pedestrian", speed=1.4, waypoints=[(0, 0, 1.2), (5, 0, 1.2), (1, 0, 1.2)])
    p = cfg.platforms[0]
    plan = plan_platform(p)
    assert plan.path.stop[1] and plan.seg_turn.any()
    t, st = dense(plan, 1e-3)
    turning = np.isin(np.searchsorted(plan.start_s + plan.seg_t0, t, side="right") - 1, np.flatnonzero(plan.seg_turn))
    turning &= (t > plan.start_s) & (t < plan.end_s)
    np.testing.assert_allclose(st["position_m"][turning], np.tile([5, 0, 1.2], (turning.sum(), 1)), atol=1e-9)
    yaw = np.unwrap(st["yaw_rad"])
    assert abs(yaw[-1] - yaw[0]) == pytest.approx(np.pi, abs=1e-9)
    rate = st["angular_velocity_radps"][:, 2]
    assert np.abs(rate).max() <= p.limits.max_yaw_rate_radps * (1 + 1e-9)
    assert (np.abs(np.diff(rate)) / 1e-3).max() <= p.limits.max_yaw_acceleration_radps2 * (1 + 1e-6)


def test_limits_have_kind_defaults_and_are_checked_in_the_config(tiny_scene):
    cfg = scene(kind="pedestrian", speed=1.0, limits={"max_speed_mps": 1.2})
    lim = cfg.platforms[0].limits
    assert lim.max_speed_mps == 1.2 and lim.max_jerk_mps3 == DEFAULT_LIMITS["pedestrian"]["max_jerk_mps3"]
    assert scene().platforms[0].limits.max_height_above_ground_m == DEFAULT_LIMITS["uav"]["max_height_above_ground_m"]
    with pytest.raises(ValueError, match="below g"):  # the config's UAV check uses the one g
        scene(limits={"max_acceleration_mps2": STANDARD_GRAVITY_MPS2})

    def problems(edit):
        raw = yaml.safe_load((TESTS / "scenes" / "tiny" / "scene.yaml").read_text())
        edit(raw)
        (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
        with pytest.raises(ConfigError) as err:
            load_scene_config(tiny_scene)
        return str(err.value)

    def uav_high(raw):
        raw["platforms"].append({"name": "drone", "kind": "uav", "trajectory": {
            "waypoints_m": [[0, 0, 30], [10, 0, 150], [20, 0, 30]], "speed_mps": 5}})

    msg = problems(uav_high)
    assert "platforms.1" in msg and "platform drone" in msg and "waypoints_m.1" in msg and "altitude band" in msg
    msg = problems(lambda raw: raw["platforms"][0]["trajectory"].update(speed_mps=30.0))
    assert "platform car0" in msg and "exceeds limits.max_speed_mps 13.9" in msg
    msg = problems(lambda raw: raw["platforms"][0].update(limits={"max_height_above_ground_m": 50.0}))
    assert "altitude band applies to UAVs only" in msg
    msg = problems(lambda raw: raw["platforms"][0].update(limits={"max_jerk_mps3": -1}))
    assert "platforms.0.limits.max_jerk_mps3" in msg
    msg = problems(lambda raw: raw["platforms"][0]["trajectory"].update(waypoints_m=[[0, 0, 1], [0, 0, 1]]))
    assert "platforms.0.trajectory.waypoints_m" in msg and "waypoints 0 and 1 coincide" in msg

    def uav_on_roads(raw):
        uav_high(raw)
        raw["platforms"][1]["trajectory"].update(waypoints_m=[[0, 0, 30], [10, 0, 30]], follow_roads=True)

    assert "follow_roads is for ground vehicles and pedestrians" in problems(uav_on_roads)


def _road_buffer(geom, min_width):
    lines, widths = roads.road_lines(geom, min_width)
    return shapely.union_all([ln.buffer(w / 2) for ln, w in zip(lines, widths)])


def _demo_with_car(waypoints, **traj):
    raw = yaml.safe_load((TESTS.parent / "scenes" / "demo" / "scene.yaml").read_text())
    # the demo's own car0 replaced by this one, as the demo's second platform
    raw["platforms"] = [p for p in raw["platforms"] if p["name"] != "car0"] + [
        {"name": "car0", "kind": "ground_vehicle", "trajectory": {"waypoints_m": waypoints, "speed_mps": 12.0, **traj}}]
    raw["clock"]["duration_s"] = 60.0
    cfg = SceneConfig.model_validate(raw)
    return cfg, source.build_source_geometry(cfg, TESTS.parent / "scenes" / "demo")


def test_ground_vehicle_on_the_demo_streets_stays_on_the_road_and_takes_a_shortest_route():
    cfg, geom = _demo_with_car([[-88.0, -50.0, 1.5], [40.0, 27.0, 1.5], [90.0, 60.0, 1.5]])
    car = cfg.platforms[1]
    cp, route = waypoint_path(car, geom)
    # Streets are a grid: any shortest route is as long as the Manhattan distance between the snaps.
    np.testing.assert_allclose(route.snapped_m[:, :2], [[-90, -50], [40, 25], [90, 60]], atol=1e-9)
    assert route.length_m == pytest.approx((130 + 75) + (50 + 35), abs=1e-6)
    ds = build_trajectory(cfg, geom=geom)
    xy = ds["position_m"].sel(platform="car0").values
    assert norm(np.diff(xy, axis=0)).sum() > 250  # it drives nearly all of it within the minute
    plan = plan_platform(car, geom)
    _, st = dense(plan, 1e-2)
    on_road = shapely.contains_xy(_road_buffer(geom, 3.0), st["position_m"][:, 0], st["position_m"][:, 1])
    assert on_road.all()
    check_clear_of_buildings(ds, geom, where="demo + car")
    assert '"follows_roads": true' in ds.attrs["dynamics"]


def test_road_route_on_a_known_graph_respects_road_widths():
    # A 100 m square ring of 6 m roads with a 2 m diagonal footway across it.
    ring = [((0, 0), (100, 0)), ((100, 0), (100, 100)), ((100, 100), (0, 100)), ((0, 100), (0, 0))]
    feats = [Feature("road", LineString(c), i + 1, width_m=6.0) for i, c in enumerate(ring)]
    feats.append(Feature("road", LineString([(0, 0), (100, 100)]), 9, width_m=2.0))
    geom = SourceGeometry(features=feats)
    wp = np.array([[2.0, -1.0, 1.5], [99.0, 98.0, 1.5]])
    car = roads.route_through(geom, wp, min_width_m=3.0, max_snap_m=5.0, waypoint_tolerance_m=1.0)
    walk = roads.route_through(geom, wp, min_width_m=0.0, max_snap_m=5.0, waypoint_tolerance_m=1.0)
    assert car.length_m == pytest.approx(98.0 + 98.0, abs=1e-9)    # (2, 0) -> (100, 0) -> (100, 98)
    assert walk.length_m == pytest.approx(2 + np.hypot(98.5, 98.5), abs=1e-9)  # to (0, 0), then the diagonal
    # Corner cuts at most half the road width (the car's corner at (100, 0)), the waypoint's tolerance at most.
    assert car.tolerance_m.max() == pytest.approx(3.0) and car.tolerance_m[0] == car.tolerance_m[-1] == 0


def test_route_matches_networkx_on_the_neukoelln_extract_and_stays_on_the_road(tmp_path):
    d = tmp_path / "nk"
    d.mkdir()
    shutil.copyfile(SHARED_DATA / "osm" / "neukolln.osm", d / "n.osm")
    cfg = SceneConfig.model_validate({
        "name": "nk", "source": {"kind": "osm", "path": "n.osm"},
        "origin": {"latitude_deg": 52.4772, "longitude_deg": 13.4366},
        "base_stations": [{"name": "bs0", "position_m": [0, 0, 50]}],
        "platforms": [{"name": "p0", "kind": "pedestrian", "trajectory": {"waypoints_m": [[0, 0, 1], [1, 0, 1]],
                                                                          "speed_mps": 1}}],
        "clock": {"duration_s": 1}})
    geom = source.build_source_geometry(cfg, d)
    lines, widths = roads.road_lines(geom, 3.0)
    pieces, _ = roads.noded_pieces(lines, widths)
    # Independent answer: networkx over every vertex of the noded centre lines.
    g = nx.Graph()
    for pc in pieces:
        xy = np.asarray(pc.coords)
        c = [tuple(np.round(x, 6)) for x in xy]
        for k, (a, b) in enumerate(zip(c[:-1], c[1:])):
            g.add_edge(a, b, weight=float(np.hypot(*(xy[k + 1] - xy[k]))))
    comp = max(nx.connected_components(g), key=len)
    nodes = sorted(comp)
    rng = np.random.default_rng(3)
    checked = []
    for _ in range(8):
        a, b = (nodes[i] for i in rng.choice(len(nodes), 2, replace=False))
        ref = nx.shortest_path_length(g, a, b, weight="weight")
        if ref < 50:
            continue
        r = roads.route_through(geom, np.array([[*a, 1.5], [*b, 1.5]]), min_width_m=3.0, max_snap_m=1.0,
                                waypoint_tolerance_m=1.0)
        assert r.length_m == pytest.approx(ref, abs=1e-5)  # waypoints are vertices to the micrometre
        checked.append((a, b, r))
    assert len(checked) >= 3
    a, b, r = checked[-1]
    # A car driving the last pair stays on the road surface and within its limits.
    plat = {"name": "car0", "kind": "ground_vehicle",
            "trajectory": {"waypoints_m": [[*a, 1.5], [*b, 1.5]], "speed_mps": 12.0}}
    car = SceneConfig.model_validate({**cfg.model_dump(), "platforms": [plat]}).platforms[0]
    plan = plan_platform(car, geom)
    assert plan.path.total_length_m <= r.length_m + 1e-6
    _, st = dense(plan, 1e-2)
    assert shapely.contains_xy(_road_buffer(geom, 3.0), st["position_m"][:, 0], st["position_m"][:, 1]).all()
    assert max(plan.limit_ratios().values()) <= 1.0


def test_waypoint_far_from_any_road_is_refused_by_name(tiny_scene):
    cfg, geom = _demo_with_car([[-90.0, -50.0, 1.5], [0.0, 0.0, 1.5]])  # (0, 0): a block's middle
    with pytest.raises(roads.RoadError) as err:
        build_trajectory(cfg, geom=geom)
    msg = str(err.value)
    assert "platform car0" in msg and "waypoint 1" in msg and "25.0 m from the nearest road" in msg
    assert "max_road_snap_distance_m" in msg
    # `simart validate` reports it too, before any asset runs, with the config key.
    raw = yaml.safe_load((tiny_scene / "scene.yaml").read_text())
    raw["platforms"][0]["trajectory"]["waypoints_m"][1] = [23.0, 0.0, 1.5]  # a block's middle, 18 m off
    (tiny_scene / "scene.yaml").write_text(yaml.safe_dump(raw))
    _, problems = scene_problems(tiny_scene)
    assert any("platforms.0.trajectory:" in p and "nearest road" in p for p in problems), problems
    # Off the roads on purpose: follow_roads false drives straight through.
    cfg, geom = _demo_with_car([[-90.0, -50.0, 1.5], [-90.0, 0.0, 1.5]], follow_roads=False)
    assert waypoint_path(cfg.platforms[1], geom)[1] is None


def test_demo_uav_stays_clear_of_buildings_over_its_whole_flight():
    cfg = load_scene_config(TESTS.parent / "scenes" / "demo")
    geom = source.build_source_geometry(cfg, TESTS.parent / "scenes" / "demo")
    plan = plan_platform(cfg.platforms[0], geom)
    longer = cfg.model_copy(update={"clock": cfg.clock.model_copy(update={"duration_s": float(np.ceil(plan.end_s))})})
    ds = build_trajectory(longer, geom=geom)
    check_clear_of_buildings(ds, geom, where="demo")
    assert norm(ds["velocity_mps"].values[0, -1]) == 0  # it arrived
    # moved into a building: a planned platform is told of its waypoints, a replayed one of its recording
    centre = geom.of_class("building")[0].geometry.representative_point()
    sunk = ds.copy(deep=True)
    sunk["position_m"][0, 10] = [centre.x, centre.y, 1.0]
    with pytest.raises(ValueError, match="inside a building.*move its waypoints"):
        check_clear_of_buildings(sunk, geom, where="demo")
    with pytest.raises(ValueError, match="inside a building.*check its recording and trajectory.recording_frame"):
        check_clear_of_buildings(sunk, geom, where="demo", replayed=["uav0"])


def test_clothoid_blend_geometry_against_its_definition():
    # Curvature linear in arc length, tangent continuous, deviation and tangent length as designed.
    cp = geo.corner_path(np.array([[0, 0, 0], [50, 0, 0], [50, 30, 10]], float), np.array([0, 2.0, 0]))
    b = int(np.flatnonzero(cp.kind == geo.BLEND)[0])
    s = np.linspace(0, cp.length_m[b], 4001)
    pos, tan, k1, _ = geo.evaluate(cp, np.full(len(s), b), s)
    kappa = norm(k1)
    lc, th = cp.half_length_m[b], cp.turn_rad[b]
    np.testing.assert_allclose(kappa, th / lc * (1 - np.abs(s - lc) / lc), atol=1e-12)
    np.testing.assert_allclose(norm(tan), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.diff(pos, axis=0) / (s[1] - s[0]), (tan[1:] + tan[:-1]) / 2, atol=1e-6)
    assert norm(pos - [50, 0, 0]).min() == pytest.approx(2.0, rel=1e-9)
    end = geo.evaluate(cp, np.array([b + 1]), np.array([0.0]))
    np.testing.assert_allclose(pos[-1], end[0][0], atol=1e-9)
    np.testing.assert_allclose(tan[-1], end[1][0], atol=1e-12)
    assert th == pytest.approx(np.pi / 2, abs=1e-12)  # (1, 0, 0) then (0, 30, 10): perpendicular
