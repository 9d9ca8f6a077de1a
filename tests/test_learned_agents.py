"""The learned agents through the registry on a served synthetic bundle: no detection (the static
agent refuses, the active one moves, adjustments counted), an object the model never saw, a
confident large detection (no move) and a small one (moves closer); no NaN or inf pose is ever
submitted and every refusal names its cause."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from brave6d.core.errors import BraveError
from brave6d.evaluation.agents import ABLATION_AGENTS, LEARNED_ACTIVE_AGENT, LEARNED_AGENTS, LEARNED_STATIC_AGENT, POLICIES, AgentSetup, \
    make_agent, run_episode, runnable_agents
from brave6d.evaluation.learned import REFUSAL_CAUSES, get_learn_preset
from brave6d.evaluation.learned.model_file import write_model
from brave6d.serve import BraveClient, ServerThread, create_app, load_bundle, make_synthetic_bundle
from learned_helpers import untrained_model

pytestmark = pytest.mark.slow
PRESET = get_learn_preset("tiny")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory):
    return load_bundle(make_synthetic_bundle(tmp_path_factory.mktemp("learned_agents"), n_gaussians=20_000))


def _model_dir(root: Path, obj_ids: list[int], name: str, detector_bias: tuple[float, float] | None = None) -> Path:
    """An untrained model; ``detector_bias`` = (heatmap logit, box side px) makes its detector see
    every object everywhere with that confidence and size."""
    model = untrained_model(PRESET, obj_ids)
    if detector_bias is not None:
        logit, side = detector_bias
        state = dict(model.detector_state)
        bias = state["heads.bias"].clone()
        weight = torch.zeros_like(state["heads.weight"])
        c = len(obj_ids)
        bias[:c], bias[c:c + 2], bias[c + 2:] = logit, math.log(side), 0.0
        state["heads.bias"], state["heads.weight"] = bias, weight
        model.detector_state = state
    folder = root / name
    folder.mkdir()
    write_model(folder, model)
    return folder


def _play(bundle, tmp_path: Path, model: Path, names: list[str], seed: int = 3):
    app = create_app(bundle, device="cpu", log_dir=tmp_path / "episodes", warm_up=False)
    target = bundle.objects[0]
    with ServerThread(app) as server, BraveClient(server.url) as client:
        out = {}
        for name in names:
            agent = make_agent(name, client, AgentSetup(learned_model=model))
            out[name] = run_episode(client, agent, target.gt_id, seed=seed, width=160, height=120)
    return out


def _check_finite(outcome) -> None:
    for est in outcome.estimates:
        assert np.all(np.isfinite(est.cam_T_obj)) and math.isfinite(est.score)
    if not outcome.estimates:
        assert outcome.notes["refused"] in REFUSAL_CAUSES and outcome.notes["refusal"]


def test_the_registry_lists_the_learned_agents_and_needs_a_model() -> None:
    assert list(POLICIES)[2:6] == list(LEARNED_AGENTS) and len(LEARNED_AGENTS) == 4
    assert list(POLICIES)[6:] == list(ABLATION_AGENTS) and len(ABLATION_AGENTS) == 6
    assert runnable_agents() == ["baseline-static", "baseline-active"]  # ablations play only when named
    assert runnable_agents(AgentSetup(learned_model=Path("m"))) == list(POLICIES)[:6]
    with pytest.raises(BraveError, match="needs a trained model"):
        make_agent(LEARNED_STATIC_AGENT, object())


def test_no_detection_static_refuses_active_moves_and_counts_adjustments(bundle, tmp_path: Path) -> None:
    ids = sorted(o.obj_id for o in bundle.objects)
    model = _model_dir(tmp_path, ids, "blind")  # an untrained detector scores 0.01 everywhere
    out = _play(bundle, tmp_path, model, list(LEARNED_AGENTS))
    for name, outcome in out.items():
        _check_finite(outcome)
        assert outcome.estimates == [] and outcome.notes["refused"] == "no-detection", name
        assert outcome.submission["submitted"]
    assert out[LEARNED_STATIC_AGENT].adjustments == 0
    active = out[LEARNED_ACTIVE_AGENT]  # moved closer (at most max_moves), then back to the start: one more
    assert 1 <= active.notes["moves"] <= 4 and active.adjustments == active.notes["moves"] + 1


def test_an_object_the_model_never_saw_is_refused_without_moving(bundle, tmp_path: Path) -> None:
    model = _model_dir(tmp_path, [901, 902], "other_library", detector_bias=(6.0, 60.0))
    out = _play(bundle, tmp_path, model, [LEARNED_STATIC_AGENT, LEARNED_ACTIVE_AGENT])
    for outcome in out.values():
        assert outcome.estimates == [] and outcome.notes["refused"] == "unknown-object"
        assert outcome.adjustments == 0


def test_a_confident_large_detection_stops_the_active_agent_and_a_small_one_moves_it(bundle, tmp_path: Path) -> None:
    ids = sorted(o.obj_id for o in bundle.objects)
    large = _play(bundle, tmp_path, _model_dir(tmp_path, ids, "large", (6.0, 120.0)), [LEARNED_ACTIVE_AGENT])
    small = _play(bundle, tmp_path, _model_dir(tmp_path, ids, "small", (6.0, 8.0)), [LEARNED_ACTIVE_AGENT])
    for outcome in (*large.values(), *small.values()):
        _check_finite(outcome)
        assert outcome.notes["detection_score_start"] > 0.99
    stayed = large[LEARNED_ACTIVE_AGENT]  # no approach: only the orbit's two looks and the way back
    assert stayed.notes["moves"] == 0 and stayed.adjustments + stayed.refused <= 3 and stayed.notes["views"] >= 1
    moved = small[LEARNED_ACTIVE_AGENT]  # its box (a corner cell of a flat heatmap) points off the table:
    assert moved.notes["moves"] >= 1 and moved.adjustments + moved.refused >= 1  # the server may refuse it
    assert moved.refused == moved.notes["refused_poses"]


@pytest.mark.parametrize("name", LEARNED_AGENTS)
def test_every_learned_agent_hands_its_estimator_the_targets_mesh(bundle, tmp_path: Path, name: str) -> None:
    # the RGB-only distance (the mask's area against the silhouette) needs it as much as the depth ICP does;
    # before, only the depth agents fetched it and an RGB agent's distance hung on which agent ran first
    ids = sorted(o.obj_id for o in bundle.objects)
    model = _model_dir(tmp_path, ids, "plain")
    app = create_app(bundle, device="cpu", log_dir=tmp_path / "episodes", warm_up=False)
    target = bundle.objects[0]
    with ServerThread(app) as server, BraveClient(server.url) as client:
        agent = make_agent(name, client, AgentSetup(learned_model=model))
        assert target.obj_id not in agent.pose_estimator.estimator.silhouettes
        _check_finite(run_episode(client, agent, target.gt_id, seed=3, width=160, height=120))
    assert target.obj_id in agent.pose_estimator.estimator.silhouettes and target.obj_id in agent.pose_estimator.estimator.surfaces


def test_held_out_recall_counts_the_detections_the_agents_use() -> None:
    from brave6d.evaluation.agents.learned.agent import LearnedAgentOptions
    from brave6d.evaluation.learned import DETECTION_THRESHOLD

    assert LearnedAgentOptions().min_score == DETECTION_THRESHOLD


class _RecordingClient(BraveClient):
    """The real client, keeping each pose the agent asked for and whether the server took it."""

    def __init__(self, url: str) -> None:
        super().__init__(url)
        self.moves: list[tuple[np.ndarray, bool]] = []

    def set_pose(self, world_T_cam, episode_id=None):  # type: ignore[no-untyped-def]
        step = super().set_pose(world_T_cam, episode_id)
        self.moves.append((np.asarray(world_T_cam, dtype=np.float64), step.accepted))
        return step


def test_an_active_agent_whose_moves_are_refused_still_submits_at_the_start_view(bundle, tmp_path: Path) -> None:
    # a detector that sees the target everywhere as a tiny box: the agent comes closer, then wants to look
    # from the sides. Replayed with the workspace shrunk around the start view and that first move (and a
    # collision box at each other pose it then took) until the server refuses everything else, the agent
    # must still fly back to the start view and submit there; before, it stayed where its refused moves
    # left it
    from dataclasses import replace

    from brave6d.serve.geometry import OrientedBox, Workspace

    ids = sorted(o.obj_id for o in bundle.objects)
    model = _model_dir(tmp_path, ids, "tiny_boxes", (6.0, 8.0))
    world, first_move = bundle.world, None
    for replay in range(6):
        app = create_app(replace(bundle, world=world), device="cpu", log_dir=tmp_path / f"episodes_{replay}",
                         warm_up=False)
        with ServerThread(app) as server, _RecordingClient(server.url) as client:
            agent = make_agent(LEARNED_ACTIVE_AGENT, client, AgentSetup(learned_model=model))
            outcome = run_episode(client, agent, bundle.objects[0].gt_id, seed=3, width=160, height=120)
        _check_finite(outcome)
        start = agent.views[0]["obs"].world_T_cam
        taken = [pose for pose, ok in client.moves if ok]
        if first_move is None:
            assert taken and not np.allclose(taken[0], start), "the agent never left the start view"
            first_move = taken[0]
            corners = np.stack([start[:3, 3], first_move[:3, 3]])
            world = replace(world, workspace=Workspace(tuple(corners.min(axis=0) - 0.01), tuple(corners.max(axis=0) + 0.01)))
            continue
        others = [p for p in taken if not (np.allclose(p, start) or np.allclose(p, first_move))]
        if not others:
            break
        world = replace(world, boxes=world.boxes + tuple(
            OrientedBox(f"blocked_{replay}_{i}", p, (1e-3, 1e-3, 1e-3)) for i, p in enumerate(others)))
    else:
        pytest.fail("the server never refused every pose but two")
    assert np.allclose(taken[0], first_move) and outcome.refused >= 2  # it came closer, then was refused ...
    assert np.allclose(taken[-1], start)  # ... and flew back to the start view and submitted there
    assert outcome.notes["refused_poses"] == outcome.refused and outcome.adjustments == len(taken)


def test_each_ablation_agent_uses_only_its_part(bundle, tmp_path: Path) -> None:
    # a detector that sees the target everywhere, a little small: the full agent would come closer,
    # look from the sides and fuse; each ablation does only its own part
    ids = sorted(o.obj_id for o in bundle.objects)
    model = _model_dir(tmp_path, ids, "smallish", (6.0, 8.0))
    out = _play(bundle, tmp_path, model, [LEARNED_ACTIVE_AGENT, "learned-active-closeness", "learned-active-selection",
                                          "learned-active-fusion"])
    for outcome in out.values():
        _check_finite(outcome)
    full, close, select, fuse = (out[n] for n in (LEARNED_ACTIVE_AGENT, "learned-active-closeness",
                                                  "learned-active-selection", "learned-active-fusion"))
    assert full.notes["moves"] >= 1 and close.notes["moves"] == full.notes["moves"]  # both come closer ...
    assert close.notes["views"] < full.notes["views"]  # ... but closeness alone looks from no side
    assert "fused" not in close.notes or close.notes["fused"] is None
    assert select.notes["moves"] == 0 == fuse.notes["moves"]  # no approach: side looks at the start distance
    assert select.notes["views"] >= 2 and fuse.notes["views"] >= 2
    if 0 in fuse.notes["posed_views"]:  # fusion alone starts from the start view's estimate (when it has one)
        assert fuse.notes["estimated_in_view"] == 0
    posed = close.notes["posed_views"]  # closeness alone takes the nearest view's
    assert not posed or close.notes["estimated_in_view"] in posed
    assert "fused" not in select.notes or select.notes["fused"] is None
