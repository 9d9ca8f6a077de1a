"""Datasets: many scenes sharing one object library, run stage by stage on a machine or a cluster.

Public API (imported lazily; ``import dataset`` loads no stage, torch or submitit):

- ``run_dataset``, ``RunSummary``: ``brave6d dataset run`` (every stage of every scene through
  submitit, resumable per scene and stage);
- ``ExecutorOptions``, ``make_executor``, ``slurm_parameters``: the submitit executor (local or
  Slurm job array) of a run;
- ``SceneJob``, ``SceneOutcome``, ``JOB_STAGES``: one scene's job (a submitit ``Checkpointable``);
- ``prepare_workdir``, ``scene_dir``, ``scene_root``, ``load_workdir_dataset``: the work directory
  (``dataset.yaml``, ``objects/``, ``scenes/<name>/``, ``status/``; a captured scene stays where it lies);
- ``RIG_STAGES``, ``check_rig_stage``: what a captured scene (``dir:``) brings from the robot, read
  from its files (``dataset run`` never runs those stages for it);
- ``read_scene_status``, ``SceneStatus``, ``read_summary``, ``status_table``, ``SCENE_STAGES``: the
  status records (``status/<scene>.json``) and the table (``status.json``);
- ``report_dataset``, ``DatasetReport``: ``brave6d dataset report`` (every scene's report and an index);
- ``LearnOptions``, ``learn_options``, ``LibraryLearnJob``, ``learned_model_dir``, ``read_learn_status``: the
  dataset's learned model, one per object library (``WORKDIR/learned/``).

The dataset spec itself (``dataset.yaml``) is read by :mod:`brave6d.core.dataset_spec`
(``load_dataset_spec``), the shared core, so that every package can read it.
Modules: ``status``, ``workdir``, ``captured``, ``job``, ``learn``, ``executor``, ``runner``, ``report``, ``cli``
(``brave6d dataset``).
The release of a dataset is the subpackage ``brave6d.dataset.release``; ``release_scene_sources`` (the
scenes of a release for the render server) is re-exported here for other stages.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "run_dataset": ".runner", "RunSummary": ".runner",
    "ExecutorOptions": ".executor", "make_executor": ".executor", "slurm_parameters": ".executor",
    "SceneJob": ".job", "SceneOutcome": ".job", "JOB_STAGES": ".job",
    "prepare_workdir": ".workdir", "scene_dir": ".workdir", "scene_root": ".workdir",
    "load_workdir_dataset": ".workdir", "RIG_STAGES": ".captured", "check_rig_stage": ".captured",
    "read_scene_status": ".status", "SceneStatus": ".status", "read_summary": ".status",
    "status_table": ".status", "SCENE_STAGES": ".status",
    "release_scene_sources": ".release.serving", "report_dataset": ".report", "DatasetReport": ".report",
    "LearnOptions": ".learn", "learn_options": ".learn", "LibraryLearnJob": ".learn",
    "learned_model_dir": ".learn", "read_learn_status": ".learn",
}

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
