"""A detector and a pose estimator written only against :mod:`brave6d.evaluation.estimators`'
interfaces (no network, nothing of brave6d's estimators: a colour threshold and the CAD model against
the depth) play the learned agents through the served HTTP API in scored mode and are scored; what
they receive is what the interface promises (depth only for the -depth agents, never ground truth),
a user's implementation loads from MODULE:FACTORY, and a wrong answer (NaN, not rigid) stops with
one line naming it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents import LEARNED_ACTIVE_AGENT, LEARNED_ACTIVE_DEPTH_AGENT, LEARNED_AGENTS, \
    LEARNED_STATIC_AGENT, LEARNED_STATIC_DEPTH_AGENT, AgentSetup, make_agent, runnable_agents
from brave6d.evaluation.estimators import Detection, Detector, EstimatedPose, EstimatorRefused, PoseEstimator, \
    checked_pose, load_factory

pytestmark = pytest.mark.slow
#: The toy scene's cubes by name, in its spec's order (brave6d.serve.toy_scene): what the detector "learned".
COLOURS = {"cube_red": (0.85, 0.1, 0.1), "cube_blue": (0.1, 0.2, 0.85)}


# ----------------------------------------------------------------------------- a user's estimator
class ColourDetector:
    """Finds each object as the largest blob of its colour (a stand-in for a user's detector)."""

    def __init__(self, colours: dict[int, tuple[float, float, float]]) -> None:
        self.colours = colours
        self.calls: list[tuple[tuple[int, ...], int | None]] = []

    def detect(self, image: np.ndarray, K: np.ndarray, obj_id: int | None = None) -> list[Detection]:
        import cv2

        self.calls.append((image.shape, obj_id))
        out = []
        for oid, rgb in self.colours.items():
            if obj_id is not None and oid != obj_id:
                continue
            distance = np.linalg.norm(image.astype(np.float64) / 255.0 - np.asarray(rgb), axis=2)
            n, _, stats, _ = cv2.connectedComponentsWithStats((distance < 0.35).astype(np.uint8))
            if n > 1:
                x, y, w, h, area = stats[1 + int(np.argmax(stats[1:, 4]))]
                out.append(Detection(oid, (float(x), float(y), float(x + w), float(y + h)), min(1.0, area / 20.0)))
        return sorted(out, key=lambda d: -d.score)


class CentroidPoseEstimator:
    """The CAD model's centre on the box's ray: at the box's median depth plus half the model's
    size with depth, else at the distance the box's size gives; the rotation the model's own."""

    def __init__(self) -> None:
        self.models: dict[int, np.ndarray] = {}
        self.depth_given: list[bool] = []

    def add_model(self, obj_id: int, vertices_m: np.ndarray, faces: np.ndarray) -> None:
        self.models[obj_id] = np.asarray(vertices_m, dtype=np.float64)

    def estimate(self, image: np.ndarray, depth_m: np.ndarray | None, K: np.ndarray,
                 detection: Detection) -> EstimatedPose:
        self.depth_given.append(depth_m is not None)
        vertices = self.models[detection.obj_id]
        centre, size = (vertices.min(0) + vertices.max(0)) / 2.0, float(np.ptp(vertices, axis=0).max())
        x0, y0, x1, y1 = detection.box
        ray = np.array([((x0 + x1) / 2 - 0.5 - K[0, 2]) / K[0, 0], ((y0 + y1) / 2 - 0.5 - K[1, 2]) / K[1, 1], 1.0])
        if depth_m is None:
            z = K[0, 0] * 1.3 * size / max(detection.size_px, 1.0)
        else:
            patch = depth_m[int(y0):int(math.ceil(y1)), int(x0):int(math.ceil(x1))]
            if not (patch > 0).any():
                raise EstimatorRefused("no-depth", "no depth inside the box")
            z = float(np.median(patch[patch > 0])) + size / 2.0
        cam_T_obj = np.eye(4)
        cam_T_obj[:3, 3] = ray * z - centre
        return EstimatedPose(cam_T_obj, detection.score)


def make_detector() -> ColourDetector:
    """A MODULE:FACTORY target: the toy scene's obj_ids number its objects in its spec's order."""
    return ColourDetector({i: COLOURS[name] for i, name in enumerate(COLOURS, start=1)})


def make_pose_estimator() -> CentroidPoseEstimator:
    return CentroidPoseEstimator()


# ----------------------------------------------------------------------------- the tests
@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve import make_synthetic_bundle

    return make_synthetic_bundle(tmp_path_factory.mktemp("protocol"), n_gaussians=20_000)


def test_a_users_estimator_plays_the_learned_agents_and_is_scored(bundle_dir: Path, tmp_path: Path) -> None:
    from brave6d.evaluation.demo import run_baselines
    from brave6d.serve import load_bundle

    bundle = load_bundle(bundle_dir)
    assert {o.name: o.obj_id for o in bundle.objects} == {"cube_red": 1, "cube_blue": 2}  # make_detector's numbering
    detector, estimator = make_detector(), make_pose_estimator()
    assert isinstance(detector, Detector) and isinstance(estimator, PoseEstimator)
    setup = AgentSetup(detector=detector, pose_estimator=estimator)
    assert runnable_agents(setup)[2:] == list(LEARNED_AGENTS)  # no trained model needed
    run = run_baselines(bundle_dir, tmp_path, device="cpu", width=160, agents=list(LEARNED_AGENTS), setup=setup)
    board = {a.agent: a for a in run.board.agents}
    print({k: (a.ar, a.mean_adjustments) for k, a in board.items()})  # the figures, for a failing run's log
    assert set(board) == set(LEARNED_AGENTS) and all(board[a].episodes == 2 for a in LEARNED_AGENTS)
    assert not run.board.not_ranked  # scored mode: every episode ranked
    # the cube is ~8 px at 160 px wide: the active agents came closer (and back), the static ones did not move
    for o in run.outcomes:
        assert o.estimates and o.notes["detection_score_start"] > 0, o.notes
        assert (o.adjustments >= 2) == (o.agent in (LEARNED_ACTIVE_AGENT, LEARNED_ACTIVE_DEPTH_AGENT)), o.agent
    # with depth the centre lands on the cube: scored above zero, and above the RGB-only guess
    assert board[LEARNED_STATIC_DEPTH_AGENT].ar > 0.1 and board[LEARNED_ACTIVE_DEPTH_AGENT].ar > 0.1
    assert board[LEARNED_STATIC_DEPTH_AGENT].ar > board[LEARNED_STATIC_AGENT].ar
    # what it was given: the target only, and depth exactly for the -depth agents (2 episodes each)
    assert {oid for _, oid in detector.calls} == {1, 2}
    static_calls = [o.notes["views"] for o in run.outcomes if o.agent in (LEARNED_STATIC_AGENT, LEARNED_STATIC_DEPTH_AGENT)]
    assert static_calls == [1, 1, 1, 1] and sum(estimator.depth_given) >= 4 and not all(estimator.depth_given)


def test_a_factory_named_module_colon_name_loads_and_a_wrong_one_is_one_line(bundle_dir: Path) -> None:
    from brave6d.serve import BraveClient, ServerThread, create_app, load_bundle

    detector = load_factory("test_estimator_protocol:make_detector", "detector")
    assert isinstance(detector, ColourDetector)
    for spec, match in (("no_such_module_xyz:f", "cannot import"), ("test_estimator_protocol:nothing", "has no"),
                        ("test_estimator_protocol", "expected MODULE:FACTORY"),
                        ("test_estimator_protocol:make_detector", "is not a PoseEstimator")):
        with pytest.raises(BraveError, match=match) as info:
            load_factory(spec, "pose_estimator")
        assert "\n" not in str(info.value)
    app = create_app(load_bundle(bundle_dir), device="cpu", warm_up=False)
    with ServerThread(app) as server, BraveClient(server.url) as client:
        agent = make_agent(LEARNED_STATIC_AGENT, client, AgentSetup(detector="test_estimator_protocol:make_detector",
                                                                    pose_estimator="registration"))
        assert isinstance(agent.detector, ColourDetector)
        with pytest.raises(BraveError, match="needs a trained model"):  # the built-in pose network needs one
            make_agent(LEARNED_STATIC_AGENT, client, AgentSetup(detector="test_estimator_protocol:make_detector"))
        with pytest.raises(BraveError, match="only a pose_estimator"):
            make_agent(LEARNED_STATIC_AGENT, client, AgentSetup(detector="registration", pose_estimator="registration"))


@pytest.mark.parametrize("matrix, match", [
    (np.full((4, 4), np.nan), "finite 4x4"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "not a rigid"),
    (np.eye(4), "behind the camera"),
])
def test_a_wrong_pose_stops_with_one_line_naming_the_estimator(matrix: np.ndarray, match: str) -> None:
    T = np.array(matrix, dtype=np.float64)
    if match != "behind the camera":
        T[2, 3] = 0.3
    with pytest.raises(BraveError, match=match) as info:
        checked_pose(EstimatedPose(T, 0.5), CentroidPoseEstimator())
    assert "CentroidPoseEstimator" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(BraveError, match="score"):
        good = np.eye(4)
        good[2, 3] = 0.3
        checked_pose(EstimatedPose(good, math.nan), CentroidPoseEstimator())


def test_the_weight_free_registration_plays_as_a_pose_estimator_and_needs_depth(bundle_dir: Path, tmp_path: Path) -> None:
    from brave6d.evaluation.demo import run_baselines

    setup = AgentSetup(detector="test_estimator_protocol:make_detector", pose_estimator="registration")
    run = run_baselines(bundle_dir, tmp_path, device="cpu", width=160, setup=setup,
                        agents=[LEARNED_STATIC_AGENT, LEARNED_STATIC_DEPTH_AGENT])
    board = {a.agent: a.ar for a in run.board.agents}
    print(board)
    assert board[LEARNED_STATIC_DEPTH_AGENT] > 0.3  # FPFH + ICP on the CAD model: the centroid's 0.26 and better
    rgb_only = [o for o in run.outcomes if o.agent == LEARNED_STATIC_AGENT]
    assert rgb_only and all(o.estimates == [] and o.notes["refused"] == "needs-depth" for o in rgb_only)


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=200, deadline=None)
@given(st.lists(finite, min_size=16, max_size=16), st.one_of(finite, st.integers(-2, 2)))
def test_no_pose_passes_the_checks_unless_finite_rigid_and_in_front(values: list[float], score: float) -> None:
    T = np.array(values, dtype=np.float64).reshape(4, 4)
    try:
        checked_pose(EstimatedPose(T, score), CentroidPoseEstimator())
    except BraveError as exc:
        assert "\n" not in str(exc) and "CentroidPoseEstimator" in str(exc)
        return
    R = T[:3, :3]
    assert np.all(np.isfinite(T)) and np.allclose(R.T @ R, np.eye(3), atol=1e-3) and T[2, 3] > 0 and 0 <= score <= 1


@settings(max_examples=200, deadline=None)
@given(st.lists(finite, min_size=4, max_size=4), finite)
def test_no_detection_passes_the_checks_unless_its_box_and_score_are_sound(box: list[float], score: float) -> None:
    from brave6d.evaluation.estimators import checked_detections

    try:
        (d,) = checked_detections([Detection(1, tuple(box), score)], ColourDetector({}), obj_id=1)  # type: ignore[arg-type]
    except BraveError as exc:
        assert "\n" not in str(exc) and "ColourDetector" in str(exc)
        return
    assert all(math.isfinite(b) for b in d.box) and d.box[2] > d.box[0] and d.box[3] > d.box[1] and 0 <= d.score <= 1
    with pytest.raises(BraveError, match="asked for object 2"):
        checked_detections([d], ColourDetector({}), obj_id=2)
