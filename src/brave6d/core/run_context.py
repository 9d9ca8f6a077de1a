"""What the stages of one pipeline run share: the typed context every stage function receives.

A stage is a function ``stage(ctx: RunContext) -> StageResult`` in its own package; the
orchestrator (:mod:`brave6d.pipeline`) names it as ``"module:function"`` and runs it with one
:class:`RunContext`, whether the run is ``brave6d demo``, one scene's job of ``brave6d dataset
run`` or a stage command (``brave6d capture run``, ``brave6d train``, ...). All of them build it
with :meth:`RunContext.for_scene`. The type lives in the core so that stages can name it (and
their commands build it) without importing the floor above them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.core.progress import StageResult
from brave6d.core.spec import SceneSpec

#: What ``--quick`` changes in a scene's capture: few views on two rings (CI's miniature runs).
QUICK_CAPTURE = {"distances_m": [0.3, 0.45], "views_per_distance": 10}
#: Where a run trains and renders: ``auto`` picks CUDA when there is one.
DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class Rig:
    """The robot and camera a run captures with, named as ``brave6d capture run`` takes them:
    ``sim`` + ``sim`` (the simulated UR5e and camera) or ``ur:HOST`` + ``oak``. The names are
    checked where the rig is opened (``brave6d.capture.open_rig``)."""

    robot: str = "sim"
    camera: str = "sim"

    @property
    def simulated(self) -> bool:
        return self.robot == "sim" and self.camera == "sim"

    def __str__(self) -> str:
        return f"--robot {self.robot} --camera {self.camera}"


#: The simulated robot and camera: the rig of ``brave6d demo`` and of a dataset's simulated scenes.
SIM_RIG = Rig()


@dataclass
class RunContext:
    """One run of the pipeline on one scene directory: what the run chose and what it did so far.

    ``workdir``: where the run keeps what is not the scene's (the demo's 3D-DAT folder, episode
    logs, report caches); ``rig``: the robot and camera of the rig stages (calibrate, capture);
    ``preset``: the training preset's name (None: the training stage's default, ``fast``);
    ``quick``: the miniature settings every stage has (few views, steps and pixels);
    ``device``: one of :data:`DEVICES`; ``obj_ids``: object name -> BOP ``obj_id`` fixed by a
    dataset's library (None: the scene numbers its own objects); ``resume``: continue a training
    from its checkpoints (a dataset job requeued after a preemption); ``results``: the stages'
    results so far, in order.
    """

    workdir: Path
    scene: SceneDir
    spec: SceneSpec
    rig: Rig = SIM_RIG
    preset: str | None = None
    quick: bool = False
    device: str = "auto"
    obj_ids: dict[str, int] | None = None
    resume: bool = False
    results: list[StageResult] = field(default_factory=list)

    @classmethod
    def for_scene(cls, scene_dir: Path | str, *, workdir: Path | str | None = None, rig: Rig = SIM_RIG,
                  preset: str | None = None, quick: bool = False, device: str = "auto",
                  obj_ids: dict[str, int] | None = None, resume: bool = False) -> RunContext:
        """The context of a run on the scene directory ``scene_dir`` (made by ``brave6d init``).

        ``workdir`` defaults to the folder that holds the scene directory (the demo's layout:
        ``WORKDIR/scene``). Raises :class:`BraveError` naming the folder when it holds no
        ``scene.yaml``, and naming the value for an unknown device; a preset name is checked by
        the training stage, which owns the presets.
        """
        scene = SceneDir(scene_dir)
        if not scene.spec_path.is_file():
            raise BraveError(f"{scene.root}: not a scene directory (no scene.yaml); create it with 'brave6d init'")
        if device not in DEVICES:
            raise BraveError(f"device {device!r}: expected one of {', '.join(DEVICES)}")
        return cls(workdir=Path(workdir) if workdir is not None else scene.root.parent, scene=scene,
                   spec=scene.load_spec(), rig=rig, preset=preset, quick=quick, device=device,
                   obj_ids=dict(obj_ids) if obj_ids is not None else None, resume=resume)
