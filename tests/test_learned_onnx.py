"""``brave6d learn export-onnx``: both networks as ONNX (opset 17, any image and crop size), ONNX
Runtime's outputs equal to torch's within ``TOLERANCE`` on sample images and crops, the estimator on
ONNX Runtime detecting and cropping as on torch and running where torch cannot be imported, a stale
or missing export refused in one line, and the missing extra named."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from brave6d.core.errors import DataError
from brave6d.evaluation.learned import LearnedEstimator, get_learn_preset
from brave6d.evaluation.learned.crops import normalise, warp_rgb
from brave6d.evaluation.learned.model_file import write_model
from brave6d.evaluation.learned.onnx_export import DETECTOR_IO, OPSET, POSE_IO, TOLERANCE, export_onnx, use_onnx
from learned_helpers import untrained_model

PRESET = get_learn_preset("tiny")
OBJECTS = [3, 5, 8]


def _model(folder: Path, seed: int = 0) -> Path:
    """An untrained model (random weights) whose batch norms hold non-trivial running statistics."""
    model = untrained_model(PRESET, OBJECTS, seed=seed)
    g = torch.Generator().manual_seed(seed)
    for state in (model.detector_state, model.pose_state):
        for key, value in state.items():
            if key.endswith("running_mean"):
                state[key] = 0.1 * torch.randn(value.shape, generator=g)
            elif key.endswith("running_var"):
                state[key] = 0.5 + torch.rand(value.shape, generator=g)
    folder.mkdir(parents=True, exist_ok=True)
    write_model(folder, model)
    return folder


def _image(seed: int, h: int, w: int) -> np.ndarray:
    """A seeded image with structure (gradients, blocks) and noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x * 255 / w, y * 255 / h, (x + y) % 64 * 4], axis=2)
    blocks = rng.integers(0, 255, (h // 16 + 1, w // 16 + 1, 3)).repeat(16, 0).repeat(16, 1)[:h, :w]
    return np.clip(0.5 * base + 0.4 * blocks + rng.normal(0, 10, (h, w, 3)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = _model(tmp_path_factory.mktemp("onnx") / "model")
    export_onnx(folder)
    return folder


def test_the_export_is_opset_17_and_checks(exported: Path) -> None:
    import onnx

    for name, (inputs, outputs) in (("detector.onnx", DETECTOR_IO), ("coordinate_net.onnx", POSE_IO)):
        graph = onnx.load(str(exported / "onnx" / name))
        onnx.checker.check_model(graph)
        assert [o.version for o in graph.opset_import if o.domain in ("", "ai.onnx")] == [OPSET] == [17]
        assert [i.name for i in graph.graph.input] == list(inputs) and [o.name for o in graph.graph.output] == list(outputs)


def test_onnx_runtime_equals_torch_on_sample_images_and_crops(exported: Path) -> None:
    import onnxruntime as ort

    torch_side = LearnedEstimator.load(exported)
    det = ort.InferenceSession(str(exported / "onnx" / "detector.onnx"), providers=["CPUExecutionProvider"])
    pose = ort.InferenceSession(str(exported / "onnx" / "coordinate_net.onnx"), providers=["CPUExecutionProvider"])
    worst = 0.0
    for seed, (h, w) in enumerate([(240, 320), (200, 320), (96, 160)]):  # sizes other than the export's example
        x = normalise(_image(seed, h, w))[None]
        with torch.no_grad():
            expected = torch_side.detector(torch.from_numpy(x))
        got = det.run(None, {"image": x})
        assert [g.shape for g in got] == [tuple(e.shape) for e in expected]
        worst = max(worst, *(float(np.abs(g - e.numpy()).max()) for g, e in zip(got, expected)))
    image = _image(7, 480, 640)
    for size in sorted({PRESET.crop_px_min, PRESET.crop_px, 96}):  # the preset's crop sides and another
        crops = np.stack([normalise(warp_rgb(image, (cx, cy), side, size))
                          for cx, cy, side in ((100.0, 80.0, 40.0), (320.0, 240.0, 150.0), (600.0, 450.0, 90.0))])
        classes = np.array([0, 2, 1], dtype=np.int64)
        with torch.no_grad():
            expected = torch_side.pose(torch.from_numpy(crops), torch.from_numpy(classes))
        for batch in (slice(0, 3), slice(1, 2)):
            got = pose.run(None, {"crops": crops[batch], "class_index": classes[batch]})
            worst = max(worst, *(float(np.abs(g - e[batch].numpy()).max()) for g, e in zip(got, expected)))
    print("largest |onnxruntime - torch|:", worst)
    assert worst <= TOLERANCE == 1e-4


def test_the_estimator_on_onnx_runtime_detects_and_crops_as_on_torch(exported: Path) -> None:
    on_torch = LearnedEstimator.load(exported)
    on_onnx = use_onnx(LearnedEstimator.load(exported), exported)
    assert on_onnx.runtime == "onnxruntime" and not isinstance(on_onnx.detector, torch.nn.Module)
    image = _image(3, 480, 640)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    a, b = on_torch.detect(image, K, min_score=0.0), on_onnx.detect(image, K, min_score=0.0)
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert x.obj_id == y.obj_id and np.allclose(x.box, y.box, atol=1e-3) and abs(x.score - y.score) < 1e-5
    box = (250.0, 180.0, 330.0, 260.0)
    for obj_id in OBJECTS:
        ct, co = on_torch._crop_outputs(image, K, obj_id, box), on_onnx._crop_outputs(image, K, obj_id, box)
        assert np.abs(ct.coords - co.coords).max() <= TOLERANCE and np.abs(ct.probability - co.probability).max() <= TOLERANCE


NO_TORCH = """
import sys
class NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(name + " blocked")
sys.meta_path.insert(0, NoTorch())
import numpy as np
from brave6d.evaluation.learned.onnx_export import OnnxEstimator
e = OnnxEstimator.from_export(sys.argv[1])
image = np.load(sys.argv[2])
K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
found = e.detect(image, K, min_score=0.0)
crop = e._crop_outputs(image, K, found[0].obj_id, (250.0, 180.0, 330.0, 260.0))
np.save(sys.argv[3], np.concatenate([[len(found), found[0].score, *found[0].box], crop.coords.ravel()]))
assert "torch" not in sys.modules
"""


def test_the_onnx_estimator_runs_without_torch_and_answers_as_torch(exported: Path, tmp_path: Path) -> None:
    image = _image(3, 480, 640)
    np.save(tmp_path / "image.npy", image)
    subprocess.run([sys.executable, "-c", NO_TORCH, str(exported / "onnx"), str(tmp_path / "image.npy"),
                    str(tmp_path / "out.npy")], check=True, timeout=120)
    got = np.load(tmp_path / "out.npy")
    on_torch = LearnedEstimator.load(exported)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    found = on_torch.detect(image, K, min_score=0.0)
    coords = on_torch._crop_outputs(image, K, found[0].obj_id, (250.0, 180.0, 330.0, 260.0)).coords
    assert got[0] == len(found) and abs(got[1] - found[0].score) < 1e-5 and np.allclose(got[2:6], found[0].box, atol=1e-3)
    assert np.abs(got[6:] - coords.ravel()).max() <= TOLERANCE


def test_a_missing_or_stale_export_is_refused_in_one_line(tmp_path: Path) -> None:
    folder = _model(tmp_path / "model")
    with pytest.raises(DataError, match="not found .*export-onnx") as info:
        use_onnx(LearnedEstimator.load(folder), folder)
    assert "\n" not in str(info.value)
    export_onnx(folder)
    _model(folder, seed=1)  # the model trained again: the export is of the old one
    with pytest.raises(DataError, match="model_sha256.*another model") as info:
        use_onnx(LearnedEstimator.load(folder), folder)
    assert "\n" not in str(info.value)


def test_the_command_line_exports_and_names_the_missing_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.cli import main

    folder = _model(tmp_path / "model")
    assert main(["learn", "export-onnx", str(folder), "--out", str(tmp_path / "out")]) == 0
    assert "opset 17" in capsys.readouterr().out
    assert {p.name for p in (tmp_path / "out").iterdir()} == {"detector.onnx", "coordinate_net.onnx", "onnx.json"}
    monkeypatch.setitem(sys.modules, "onnx", None)  # as if not installed
    assert main(["learn", "export-onnx", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "needs the 'onnx' extra" in err and "pip install 'brave6d[onnx]'" in err


def test_the_learned_agents_play_on_onnx_runtime(exported: Path, tmp_path: Path) -> None:
    from brave6d.evaluation.agents import LEARNED_ACTIVE_DEPTH_AGENT, AgentSetup, make_agent, run_episode
    from brave6d.serve import BraveClient, ServerThread, create_app, load_bundle, make_synthetic_bundle

    bundle = load_bundle(make_synthetic_bundle(tmp_path / "scene", n_gaussians=5_000))
    setup = AgentSetup(learned_model=exported, detector="learned-onnx", pose_estimator="learned-onnx")
    with ServerThread(create_app(bundle, device="cpu", warm_up=False)) as server, BraveClient(server.url) as client:
        agent = make_agent(LEARNED_ACTIVE_DEPTH_AGENT, client, setup)
        assert agent.detector.estimator.runtime == agent.pose_estimator.estimator.runtime == "onnxruntime"
        outcome = run_episode(client, agent, bundle.objects[0].gt_id, seed=3, width=160, height=120)
    # this untrained model knows objects 3, 5, 8, not the toy scene's: refused by name, as on torch
    assert outcome.estimates == [] and outcome.notes["refused"] == "unknown-object"
