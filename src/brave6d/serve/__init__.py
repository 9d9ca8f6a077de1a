"""Serve stage: scene bundles, the render server, its Python client and wire/log schemas, a
Gymnasium environment and a browser viewer.

Public API (imported lazily, so ``import serve`` stays cheap: no torch, FastAPI or pydantic until
a name is used). Other stages import only these names:

- bundles: ``export_bundle``, ``load_bundle``, ``Bundle``, ``BundleObject``, ``BundleError``,
  ``read_bundle_manifest`` (the one reader of a bundle's ``manifest.json``, structure checked),
  ``is_bundle`` (the one test for a bundle folder), ``find_splat_ply``, ``MANIFEST``, ``SPLAT``,
  ``SPLAT_VIEWER`` and ``HOLDOUT_IMAGES`` (the manifest's, the splat's and the viewer splat's file
  names and the holdout images' folder inside
  a bundle: the bundle's names live in :mod:`brave6d.serve.bundle` only);
- the server: ``create_app``, ``validate_request`` (a request checked as HTTP checks it: same limits and
  messages, for the ROS 2 node), ``ServerLimits`` (its limits, checked when made: ``LimitError``;
  ``limit_arg(name)``: the argparse type of the flag setting one), ``ServerThread`` (uvicorn in a
  background thread),
  ``SceneServer``, ``SplatRenderer``, ``EpisodeManager`` (episodes without HTTP);
- the scenes of a server (:mod:`brave6d.serve.catalog`): ``open_scenes`` (scene sources, or a bundle
  folder), ``SourcesOf`` (what the command line hands a serving command: path -> sources; a release's
  come from ``brave6d.dataset``, which serve never imports),
  ``SceneCatalog`` (lazy loading within a memory bound), ``SceneSource``, ``SceneObject``,
  ``bundle_scene_source``, ``estimate_scene_bytes``, ``listed_scene_bytes`` (which files count),
  ``SceneCacheFull``, ``SceneUnavailable`` (503:
  a scene whose files cannot be located, unpacked or verified, even after ``SceneSource.refresh``);
- the client: ``BraveClient``, ``PoseEstimate``, ``ServerError``, ``Observation``, ``StepResult``,
  ``decode_observation``, and ``BraveEnv`` (a ``gymnasium.Env``); ``BraveVectorEnv`` (a
  ``gymnasium.vector.VectorEnv``: N agents on one scene in process, their renders batched); what a
  client reads of a server it does not trust (:mod:`brave6d.serve.replies`): ``ClientLimits``,
  ``ReplyError``, ``parse_reply``; the largest image, ``MAX_WIDTH`` x ``MAX_HEIGHT``;
- the wire schema (:mod:`brave6d.serve.schema`): ``ObservationMessage``, ``StepMessage``, ``ObjectState``,
  ``EncodedImage``, ``TargetRef``, ``ErrorMessage``;
- the episode log (:mod:`brave6d.serve.episode_log`, versioned): ``read_episode_log``, ``EpisodeLog``,
  ``ResetRecord``, ``ActionRecord``, ``SubmitRecord``, ``CloseRecord``, ``LoggedEstimate``,
  ``FinalView``, ``LOG_FORMAT_VERSION``, ``FINAL_DEPTH_SUFFIX``;
- the reference geometry scores are measured against (:mod:`brave6d.serve.reference`):
  ``build_scene_reference``, ``ReferenceSettings``, ``ReferenceGeometry`` (depth by ray casting),
  ``read_reference``, ``ReferenceGeometryError``, ``REFERENCE`` (its file name in a bundle);
- test scenes: ``make_synthetic_bundle``, ``make_synthetic_scene``;
- the modes (:mod:`brave6d.serve.modes`): ``SCORED`` (the default: no ground truth reaches an agent),
  ``TRAINING``, ``MODES``, ``check_mode``, ``public_bundle`` (``GET /bundle`` as a mode shows it); the
  serving commands' flags ``add_mode_flags`` (``--training``, ``--log-key``) and ``mode_of``;
- the episode logs' keyed digest (:mod:`brave6d.serve.log_digest`): ``LogKey``, ``server_log_key`` (made on
  first use), ``evaluation_log_key``, ``read_log_key``, ``default_log_key_path``, ``LOG_KEY_ENV``,
  ``check_log_digest``, ``DigestCheck``, and the log's ``DigestRecord``.

The modules behind them, one job each: ``bundle`` (export + verified load), ``limits`` (image-size
cap, pose and twist bounds, the server's limits and the bounds of its flags), ``connections``
(header/body timeouts, per-client connection cap), ``geometry`` (collisions, twist integration),
``renderer`` (the splat on cuda/cpu), ``catalog`` (the scenes of a server), ``splat_check``,
``visibility`` (visible fractions), ``reference`` (the reference geometry), ``episodes`` (the episode state machine), ``episode_manager``
(runs the episodes of a catalog), ``schema`` (wire
models), ``episode_log`` (log schema, writer, reader), ``app`` (FastAPI: REST + WebSocket +
viewer), ``client``, ``gym_env``, ``runner`` (uvicorn), ``cli`` and ``export_cli`` (``brave6d
serve``/``export``), ``demo``, ``synthetic``, ``modes`` (what each mode shows), ``log_digest`` (the
logs' keyed digest); ``serve/viewer/`` is the static browser viewer
served at ``/viewer/``.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "export_bundle": ".bundle", "load_bundle": ".bundle", "Bundle": ".bundle", "BundleObject": ".bundle",
    "BundleError": ".bundle", "read_bundle_manifest": ".bundle", "find_splat_ply": ".bundle", "SPLAT": ".bundle",
    "SPLAT_VIEWER": ".bundle",
    "HOLDOUT_IMAGES": ".bundle",
    "create_app": ".app", "validate_request": ".app", "ServerLimits": ".limits", "LimitError": ".limits", "limit_arg": ".limits",
    "ServerThread": ".runner", "SceneServer": ".episodes",
    "SplatRenderer": ".renderer", "EpisodeManager": ".episode_manager",
    "open_scenes": ".catalog", "SceneCatalog": ".catalog", "SceneSource": ".catalog", "SceneObject": ".catalog",
    "bundle_scene_source": ".catalog", "estimate_scene_bytes": ".catalog", "listed_scene_bytes": ".catalog",
    "SceneCacheFull": ".catalog",
    "SourcesOf": ".catalog", "is_bundle": ".bundle", "MANIFEST": ".bundle",
    "SceneUnavailable": ".catalog",
    "BraveClient": ".client", "PoseEstimate": ".client", "ServerError": ".client", "Observation": ".client",
    "StepResult": ".client", "decode_observation": ".client", "BraveEnv": ".gym_env",
    "ReplyError": ".replies", "ClientLimits": ".replies", "parse_reply": ".replies",
    "MAX_WIDTH": ".limits", "MAX_HEIGHT": ".limits",
    "BraveVectorEnv": ".vector_env",
    "ObservationMessage": ".schema", "StepMessage": ".schema", "ObjectState": ".schema",
    "EncodedImage": ".schema", "TargetRef": ".schema", "ErrorMessage": ".schema",
    "read_episode_log": ".episode_log", "EpisodeLog": ".episode_log", "ResetRecord": ".episode_log",
    "ActionRecord": ".episode_log", "SubmitRecord": ".episode_log", "CloseRecord": ".episode_log",
    "LoggedEstimate": ".episode_log", "FinalView": ".episode_log", "LOG_FORMAT_VERSION": ".episode_log",
    "FINAL_DEPTH_SUFFIX": ".episode_log",
    "build_scene_reference": ".reference", "ReferenceSettings": ".reference", "ReferenceGeometry": ".reference",
    "ReferenceGeometryError": ".reference", "read_reference": ".reference", "REFERENCE": ".bundle",
    "make_synthetic_bundle": ".toy_scene", "make_synthetic_scene": ".toy_scene",
    "SCORED": ".modes", "TRAINING": ".modes", "MODES": ".modes", "check_mode": ".modes", "public_bundle": ".modes",
    "add_mode_flags": ".cli", "mode_of": ".cli",
    "LogKey": ".log_digest", "server_log_key": ".log_digest", "evaluation_log_key": ".log_digest",
    "read_log_key": ".log_digest", "default_log_key_path": ".log_digest", "LOG_KEY_ENV": ".log_digest",
    "check_log_digest": ".log_digest", "DigestCheck": ".log_digest", "DigestRecord": ".episode_log",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
