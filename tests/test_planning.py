"""Collision primitives (analytic cases) and the view planner (coverage, checks, order, plan.json)."""

from __future__ import annotations

import itertools
import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DataError
from brave6d.core.spec import parse_scene_spec
from brave6d.core.transforms import make_transform
from brave6d.capture.collision import (
    BoxSet,
    ToolModel,
    arm_collisions,
    obb_overlaps,
    points_in_boxes,
    segment_hits,
    tool_collisions,
)
from brave6d.capture.kinematics import URKinematics
from brave6d.capture.planning import (
    PlannerOptions,
    choose_representatives,
    fibonacci_cap,
    load_plan,
    order_views,
    path_travel_time,
    plan_views,
    plot_plan,
    sample_viewpoints,
    save_plan,
)
from brave6d.capture.sim_robot import SimRobot


def rot(rpy_deg: tuple[float, float, float]) -> np.ndarray:
    return Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()


UNIT = BoxSet.from_arrays(np.eye(4)[None], [[1.0, 1.0, 1.0]], ["unit"])


# ============================================================================ collision primitives
@pytest.mark.parametrize("x, margin, expected", [
    (0.99, 0.0, True),   # overlapping
    (1.0, 0.0, True),    # touching faces counts as contact
    (1.01, 0.0, False),  # 1 cm gap
    (1.01, 0.02, True),  # ... but inside the safety margin
    (1.03, 0.02, False),
])
def test_obb_face_contact(x: float, margin: float, expected: bool) -> None:
    T = make_transform(np.eye(3), [x, 0.0, 0.0])
    assert obb_overlaps(T, [0.5, 0.5, 0.5], UNIT, margin).tolist() == [expected]


def test_obb_rotated_corner_contact() -> None:
    """Unit cube turned 45 deg about z reaches sqrt(0.5) along x: contact at x = 0.5 + sqrt(0.5)."""
    edge = 0.5 + math.sqrt(0.5)
    for dx, expected in ((-1e-6, True), (1e-6, False)):
        T = make_transform(rot((0, 0, 45)), [edge + dx, 0.0, 0.0])
        assert obb_overlaps(T, [0.5, 0.5, 0.5], UNIT).tolist() == [expected]


@pytest.mark.parametrize("z, expected", [(0.15, False), (0.13, True)])
def test_obb_edge_edge_separation_needs_cross_axes(z: float, expected: bool) -> None:
    """Two crossing rods, each turned 45 deg about its own long axis: only the cross-product axis
    x X y = z separates them (gap iff z > 2 * 0.05 * sqrt(2) = 0.1414); face axes never do."""
    rod_a = BoxSet.from_arrays(make_transform(rot((45, 0, 0)), [0, 0, 0])[None], [[2.0, 0.1, 0.1]], ["a"])
    T_b = make_transform(rot((0, 45, 0)), [0.0, 0.0, z])
    assert obb_overlaps(T_b, [0.05, 1.0, 0.05], rod_a).tolist() == [expected]


def test_obb_vectorised_over_boxes_and_names() -> None:
    boxes = BoxSet.from_arrays(
        np.stack([make_transform(np.eye(3), [0, 0, 0]), make_transform(rot((0, 0, 30)), [3, 0, 0]),
                  make_transform(np.eye(3), [0, 3, 0])]),
        [[1, 1, 1], [1, 1, 1], [1, 1, 1]], ["a", "b", "c"])
    T = make_transform(np.eye(3), [2.5, 0.0, 0.0])
    assert obb_overlaps(T, [0.2, 0.2, 0.2], boxes).tolist() == [False, True, False]
    assert obb_overlaps(T, [0.2, 0.2, 0.2], BoxSet.empty()).shape == (0,)


@settings(max_examples=80, deadline=None)
@given(c=st.tuples(*[st.floats(-1.2, 1.2)] * 3), rpy=st.tuples(*[st.floats(-180, 180)] * 3),
       h=st.tuples(*[st.floats(0.05, 0.6)] * 3))
def test_obb_agrees_with_point_sampling(c, rpy, h) -> None:
    """Sampled points of the query box inside the unit box imply overlap; a 'separated' answer
    implies that no sampled point lies inside (an independent, one-sided check both ways)."""
    T = make_transform(rot(rpy), c)
    g = np.linspace(-1.0, 1.0, 7)
    local = np.stack(np.meshgrid(g, g, g), axis=-1).reshape(-1, 3) * np.asarray(h)
    pts = local @ T[:3, :3].T + T[:3, 3]
    any_inside = bool(points_in_boxes(pts, UNIT).any())
    overlap = bool(obb_overlaps(T, h, UNIT)[0])
    if any_inside:
        assert overlap
    if not overlap:
        assert not any_inside


def test_segment_box_cases() -> None:
    assert segment_hits([-2, 0, 0], [2, 0, 0], UNIT).tolist() == [True]  # straight through
    assert segment_hits([-2, 0.6, 0], [2, 0.6, 0], UNIT).tolist() == [False]  # parallel, outside
    assert segment_hits([-2, 0.6, 0], [2, 0.6, 0], UNIT, radius=0.11).tolist() == [True]  # capsule
    assert segment_hits([-2, 0.6, 0], [2, 0.6, 0], UNIT, radius=0.05, margin=0.06).tolist() == [True]
    assert segment_hits([0.1, 0.1, 0.1], [0.2, 0.2, 0.2], UNIT).tolist() == [True]  # inside
    assert segment_hits([2, 2, 2], [3, 3, 3], UNIT).tolist() == [False]
    assert segment_hits([-2, 0, 0], [-0.6, 0, 0], UNIT).tolist() == [False]  # stops short
    assert segment_hits([-2, 0, 0], [-0.5, 0, 0], UNIT).tolist() == [True]  # ends on the face
    # diagonal passing a rotated box's corner
    box45 = BoxSet.from_arrays(make_transform(rot((0, 0, 45)), [0, 0, 0])[None], [[1, 1, 1]])
    assert segment_hits([0.70, -1, 0], [0.70, 1, 0], box45).tolist() == [True]
    assert segment_hits([0.72, -1, 0], [0.72, 1, 0], box45).tolist() == [False]


def test_tool_collisions_name_the_part_and_box() -> None:
    table = BoxSet.from_arrays(make_transform(np.eye(3), [0.5, 0, -0.25])[None], [[1, 1, 0.5]], ["table"])
    tool = ToolModel(base_half_width=0.0)
    flange = make_transform(np.diag([1.0, -1.0, -1.0]), [0.5, 0.0, 0.2])  # pointing down, 20 cm up
    cam = flange @ make_transform(np.eye(3), [0, -0.06, 0.03])
    assert tool_collisions(flange, cam, table, tool, wrist_length=0.1) == []
    low = flange.copy()
    low[2, 3] = 0.005
    cam_low = low @ make_transform(np.eye(3), [0, -0.06, 0.03])
    hits = tool_collisions(low, cam_low, table, tool, wrist_length=0.1)
    assert "camera body vs 'table'" in hits and "flange vs 'table'" in hits
    # the robot's own base box
    near_base = make_transform(np.diag([1.0, -1.0, -1.0]), [0.05, 0.0, 0.2])
    assert any("robot base (self)" in h for h in tool_collisions(near_base, near_base, BoxSet.empty(), ToolModel()))


def test_arm_collisions_with_a_low_box() -> None:
    kin = URKinematics("ur5e")
    q = np.deg2rad([0, -90, 90, -90, -90, 0])  # forearm horizontal at z = d1 + |a2| = 0.5875
    frames = kin.link_frames(q)
    shelf = BoxSet.from_arrays(make_transform(np.eye(3), [-0.2, -0.13, 0.5875])[None], [[0.1, 0.3, 0.02]], ["shelf"])
    assert any(h.startswith("forearm vs 'shelf'") for h in arm_collisions(frames, shelf))
    far = BoxSet.from_arrays(make_transform(np.eye(3), [1.5, 1.5, 0])[None], [[0.1, 0.1, 0.1]], ["far"])
    assert arm_collisions(frames, far) == []


# ============================================================================ sampling
def test_fibonacci_cap_is_uniform_by_area() -> None:
    n, lo, hi = 3000, math.radians(20), math.radians(85)
    az, el = fibonacci_cap(n, lo, hi)
    assert np.all(el >= lo) and np.all(el <= hi)
    # equal-area bands = equal steps in sin(elevation): each of 10 bands holds n / 10 (+-1)
    edges = np.linspace(math.sin(lo), math.sin(hi), 11)
    counts = np.histogram(np.sin(el), edges)[0]
    assert np.all(np.abs(counts - n / 10) <= 1)
    # and NOT equal steps in the elevation angle: the top band (small area) holds far fewer
    ang_counts = np.histogram(el, np.linspace(lo, hi, 11))[0]
    expected = n * np.diff(np.sin(np.linspace(lo, hi, 11))) / (math.sin(hi) - math.sin(lo))
    assert np.all(np.abs(ang_counts - expected) <= 2)
    assert ang_counts[-1] < 0.3 * ang_counts[0]
    # azimuth: uniform in 12 sectors within each elevation half
    for half in (el < np.median(el), el >= np.median(el)):
        c = np.histogram(az[half], np.linspace(-math.pi, math.pi, 13))[0]
        assert np.all(np.abs(c - half.sum() / 12) <= 0.1 * half.sum() / 12 + 2)


def test_uniform_in_angle_sampler_would_fail_the_area_check() -> None:
    """The area check above can fail: an elevation-uniform sampler over-fills the top bands."""
    lo, hi, n = math.radians(20), math.radians(85), 3000
    el = lo + (np.arange(n) + 0.5) / n * (hi - lo)
    counts = np.histogram(np.sin(el), np.linspace(math.sin(lo), math.sin(hi), 11))[0]
    assert not np.all(np.abs(counts - n / 10) <= 1)


def _spec(**overrides: Any):
    data: dict[str, Any] = {
        "name": "plan_test",
        "capture": {"target": [0.45, 0.0, 0.01], "distances_m": [0.25, 0.4], "views_per_distance": 36,
                    "min_elevation_deg": 30, "max_elevation_deg": 85, "settle_time_s": 0.2},
        "workspace": {"min": [0.0, -0.6, 0.02], "max": [0.94, 0.6, 0.9]},
        "collision_boxes": [
            {"name": "table", "center": [0.55, 0.0, -0.375], "size": [0.8, 1.0, 0.75]},
            {"name": "pedestal", "center": [0.0, 0.0, -0.4], "size": [0.2, 0.2, 0.8]},
            {"name": "wall", "center": [0.96, 0.0, 0.4], "size": [0.02, 1.6, 0.8]},
        ],
        "robot": {"model": "ur5e", "tcp_T_camera_guess": {"xyz": [0.0, -0.06, 0.03]}},
    }
    for key, value in overrides.items():
        section, _, field = key.partition("__")
        if field:
            data[section] = {**data[section], field: value}
        else:
            data[section] = value
    return parse_scene_spec(data, check_files=False)


def test_viewpoints_look_at_the_target_with_the_roll_convention() -> None:
    spec = _spec()
    vps = sample_viewpoints(spec.capture)
    assert len(vps) == 72
    assert [sum(v.distance_level == k for v in vps) for k in (0, 1)] == [36, 36]
    target = np.array(spec.capture.target)
    for v in vps:
        T = v.base_T_cam
        eye, z = T[:3, 3], T[:3, 2]
        to_t = target - eye
        assert np.linalg.norm(np.cross(z, to_t)) < 1e-9  # the optical axis passes through the target
        assert z @ to_t == pytest.approx(v.distance_m, abs=1e-9)  # in front, at the ring distance
        assert abs(T[:3, 0] @ [0, 0, 1]) < 1e-9  # image x horizontal (no roll)
        assert -T[:3, 1] @ [0, 0, 1] > 0  # image up points to world +z
        assert math.degrees(v.elevation) == pytest.approx(
            math.degrees(math.asin((eye[2] - target[2]) / v.distance_m)), abs=1e-9)


def test_pole_views_are_finite() -> None:
    spec = _spec(capture__min_elevation_deg=89.9, capture__max_elevation_deg=90.0, capture__views_per_distance=3)
    for v in sample_viewpoints(spec.capture):
        assert np.all(np.isfinite(v.base_T_cam))
        np.testing.assert_allclose(v.base_T_cam[:3, :3].T @ v.base_T_cam[:3, :3], np.eye(3), atol=1e-12)


# ============================================================================ the planner
@pytest.fixture(scope="module")
def plan_and_spec():
    spec = _spec()
    return plan_views(spec), spec


def test_plan_views_are_exact_reachable_and_collision_free(plan_and_spec) -> None:
    plan, spec = plan_and_spec
    kin = URKinematics("ur5e")
    tcp_T_cam = spec.robot.tcp_T_camera_guess.matrix()
    boxes = BoxSet.from_specs(spec.collision_boxes)
    assert len(plan.views) > 40
    for v in plan.views:
        np.testing.assert_allclose(kin.fk(v.joints), v.base_T_tcp, atol=1e-9)
        np.testing.assert_allclose(v.base_T_tcp @ tcp_T_cam, v.base_T_cam, atol=1e-12)
        assert kin.within_limits(v.joints)
        assert kin.branch_of(v.joints) == plan.configuration  # one arm configuration throughout
        assert tool_collisions(v.base_T_tcp, v.base_T_cam, boxes, ToolModel(), kin.dh.d6) == []
        assert arm_collisions(kin.link_frames(v.joints), boxes) == []
        assert np.all(v.base_T_cam[:3, 3] >= np.array(spec.workspace.min))
        assert np.all(v.base_T_cam[:3, 3] <= np.array(spec.workspace.max))


def test_every_view_is_planned_or_dropped_with_a_reason(plan_and_spec) -> None:
    plan, _ = plan_and_spec
    planned = [v.view_id for v in plan.views]
    dropped = [d.view_id for d in plan.dropped]
    assert len(set(planned)) == len(planned)
    assert sorted(planned + dropped) == list(range(72))
    assert plan.views_per_ring() == {k: sum(v.distance_level == k for v in plan.views) for k in (0, 1)}
    assert plan.dropped  # the far side of the large ring is out of reach
    for d in plan.dropped:
        assert d.reason.startswith(("unreachable: ", "collision: ", "outside the workspace: ", "arm collision",
                                    "reachable only in another arm configuration"))


def test_order_beats_sampling_order_without_flips(plan_and_spec) -> None:
    plan, spec = plan_and_spec
    path = plan.joint_path()
    speed, acc = spec.robot.joint_speed, spec.robot.joint_acceleration
    assert plan.travel_time_s == pytest.approx(path_travel_time(path, speed, acc))
    assert plan.travel_time_s < 0.6 * plan.naive_travel_time_s
    steps = np.abs(np.diff(path[1:], axis=0)).max(axis=1)  # between views (not the first move)
    assert steps.max() == pytest.approx(plan.max_joint_step_rad)
    assert steps.max() < math.radians(120)
    assert np.median(steps) < math.radians(25)
    assert len(set(np.sign(np.sin(path[1:, 4])).tolist())) == 1  # q5 never crosses 0/pi: no wrist flip
    # the same moves on the simulated robot take the estimated time
    robot = SimRobot(spec.robot)
    for v in plan.views:
        robot.move_to(v.base_T_tcp)
        np.testing.assert_allclose(robot.joints(), v.joints, atol=1e-6)
    assert robot.now() == pytest.approx(plan.travel_time_s, rel=1e-6)


def test_rings_order_keeps_rings_together() -> None:
    plan = plan_views(_spec(), options=PlannerOptions(order="rings"))
    levels = [v.distance_level for v in plan.views]
    assert levels == sorted(levels)
    none = plan_views(_spec(), options=PlannerOptions(order="none"))
    assert [v.view_id for v in none.views] == sorted(v.view_id for v in none.views)
    assert none.travel_time_s == pytest.approx(none.naive_travel_time_s)
    assert plan.travel_time_s < none.travel_time_s


def test_order_views_solves_a_line() -> None:
    rng = np.random.default_rng(3)
    pos = rng.permutation(25) * 0.1
    joints = np.zeros((25, 6))
    joints[:, 0] = pos
    order = order_views(joints, np.zeros(6), 1.0, 1.4)
    assert sorted(order) == list(range(25))
    np.testing.assert_allclose(joints[order, 0], np.sort(pos))  # walk the line from the start


def test_order_views_is_near_optimal_on_small_instances() -> None:
    rng = np.random.default_rng(0)
    for _ in range(10):
        q = rng.uniform(-2.0, 2.0, (7, 6))
        allq = np.vstack([np.zeros((1, 6)), q])
        cost = np.zeros((8, 8))
        for i, a in enumerate(allq):
            for j, b in enumerate(allq):
                cost[i, j] = path_travel_time(np.stack([a, b]), 1.05, 1.4)

        def total(p: tuple[int, ...]) -> float:
            return cost[0, p[0] + 1] + sum(cost[a + 1, b + 1] for a, b in zip(p[:-1], p[1:]))

        best = min(total(p) for p in itertools.permutations(range(7)))
        assert total(tuple(order_views(q, np.zeros(6), 1.05, 1.4))) <= 1.05 * best


def test_explicit_configuration_drops_views_of_other_configurations() -> None:
    auto = plan_views(_spec())
    cfg = (1, 1, 1)
    plan = plan_views(_spec(), options=PlannerOptions(configuration=cfg))
    assert plan.configuration == cfg
    kin = URKinematics("ur5e")
    assert plan.views and all(kin.branch_of(v.joints) == cfg for v in plan.views)
    other = [d for d in plan.dropped if d.reason.startswith("reachable only in another arm configuration")]
    assert other and all("the plan keeps (shoulder +, elbow +, wrist +)" in d.reason for d in other)
    assert len(auto.views) >= len(plan.views)


def test_representatives_never_wind_a_joint() -> None:
    q = np.zeros((40, 6))
    q[:, 5] = np.linspace(-math.pi, math.pi, 40, endpoint=False) + 0.05  # a full turn of joint 6
    reps = choose_representatives(q, np.zeros(6), np.tile([-2 * math.pi, 2 * math.pi], (6, 1)))
    assert np.ptp(reps[:, 5]) < 2 * math.pi
    np.testing.assert_allclose(np.cos(reps - q), 1.0, atol=1e-12)  # same angles, whole turns apart


def test_drops_name_their_reason() -> None:
    # a box over the near half of the small ring: those views collide with it
    spec = _spec(collision_boxes=[{"name": "lamp", "center": [0.3, 0.0, 0.2], "size": [0.3, 1.0, 0.3]}])
    plan = plan_views(spec)
    lamp = [d for d in plan.dropped if "'lamp'" in d.reason]
    assert lamp and all(d.reason.startswith(("collision", "arm collision")) for d in lamp)
    # a low workspace ceiling drops the high views
    plan = plan_views(_spec(workspace={"min": [-1, -1, 0.0], "max": [1.5, 1, 0.2]}))
    high = [d for d in plan.dropped if "workspace" in d.reason]
    assert high and all("above the workspace maximum" in d.reason for d in high)
    assert plan.views and all(v.base_T_cam[2, 3] <= 0.2 for v in plan.views)
    # a target out of reach: everything dropped as unreachable
    far = plan_views(_spec(capture__target=[1.8, 0.0, 0.0], workspace={"min": [-3, -3, -1], "max": [3, 3, 3]},
                           collision_boxes=[]))
    assert far.views == [] and all(d.reason.startswith("unreachable") for d in far.dropped)
    assert far.travel_time_s == 0.0


def test_plan_json_round_trip(tmp_path, plan_and_spec) -> None:
    plan, _ = plan_and_spec
    path = save_plan(plan, tmp_path / "capture" / "plan.json")
    loaded = load_plan(path)
    assert [v.view_id for v in loaded.views] == [v.view_id for v in plan.views]
    for a, b in zip(loaded.views, plan.views):
        np.testing.assert_array_equal(a.joints, b.joints)
        np.testing.assert_array_equal(a.base_T_tcp, b.base_T_tcp)
        np.testing.assert_array_equal(a.base_T_cam, b.base_T_cam)
        assert (a.azimuth, a.elevation, a.distance_m, a.distance_level) == (
            b.azimuth, b.elevation, b.distance_m, b.distance_level)
    assert [(d.view_id, d.reason) for d in loaded.dropped] == [(d.view_id, d.reason) for d in plan.dropped]
    assert loaded.configuration == plan.configuration
    assert loaded.travel_time_s == plan.travel_time_s and loaded.estimated_time_s == plan.estimated_time_s
    np.testing.assert_array_equal(loaded.tcp_T_cam, plan.tcp_T_cam)
    # corrupt files give a DataError naming the file
    bad = tmp_path / "bad.json"
    data = json.loads(path.read_text())
    del data["views"][0]["joints"]
    bad.write_text(json.dumps(data))
    with pytest.raises(DataError, match="bad.json"):
        load_plan(bad)
    (tmp_path / "trunc.json").write_text(path.read_text()[:100])
    with pytest.raises(DataError, match="trunc.json"):
        load_plan(tmp_path / "trunc.json")


def test_plot_plan_writes_a_png(tmp_path, plan_and_spec) -> None:
    plan, spec = plan_and_spec
    out = plot_plan(plan, tmp_path / "plan.png", BoxSet.from_specs(spec.collision_boxes), spec.workspace)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
