"""A small synthetic scene directory (and bundle) for tests and benchmarks of the render server.

:func:`make_synthetic_scene` writes, without running the pipeline, what the earlier stages would:

* ``scene.yaml``: a tabletop (table box with its top at z = 0), a wall and a tall ``post`` as
  collision boxes, the demo's workspace, two cube objects (20 mm, meshes in mm);
* ``splat/point_cloud.ply`` (Inria layout): a checkered table of flat Gaussians, the wall, the
  post and the two cubes' faces (red and blue), ``n_gaussians`` in all (most on the table), and
  ``splat/holdout.json`` (the trainer's rule on the frames below, as a training records it);
* ``annotation/objects.json`` (``brave6d-annotation/1``) with the cubes' world poses;
* ``calibration/intrinsics.json`` (no distortion) and ``handeye.json`` (identity), and
  ``capture/frames.jsonl`` with ``n_views`` views on a ring looking at the objects and plain
  PNG frames, so that holdout views and the annotation's BOP export can be made from it; with
  ``depth=True`` also the true depth of every frame (:func:`true_mesh` ray cast at the frame's
  pose, uint16 mm), so that the bundle gets a reference geometry whose truth is known.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import write_png
from brave6d.core.calibration_io import write_handeye, write_intrinsics
from brave6d.core.camera import PinholeCamera
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
from brave6d.core.transforms import look_at, make_transform, rpy_deg_to_matrix

CUBE_MM = 20.0
#: World poses of the two cubes (their model origin is the cube's bottom-face centre).
CUBE_POSES = {
    "cube_red": ((0.45, -0.03, 0.0), (0.0, 0.0, 15.0)),
    "cube_blue": ((0.47, 0.04, 0.0), (0.0, 0.0, -30.0)),
}
CUBE_COLOURS = {"cube_red": (0.85, 0.1, 0.1), "cube_blue": (0.1, 0.2, 0.85)}
TARGET = (0.46, 0.0, 0.01)
POST = {"name": "post", "center": [0.30, 0.25, 0.15], "size": [0.06, 0.06, 0.30]}

SPEC = {
    "name": "synthetic_tabletop",
    "category": "mixed",
    "capture": {"target": list(TARGET), "distances_m": [0.25, 0.35], "views_per_distance": 6,
                "min_elevation_deg": 30, "max_elevation_deg": 80, "depth": False},
    "workspace": {"min": [0.0, -0.6, 0.02], "max": [0.94, 0.6, 0.9]},
    "collision_boxes": [
        {"name": "table", "center": [0.55, 0.0, -0.375], "size": [0.80, 1.00, 0.75]},
        {"name": "wall", "center": [0.96, 0.0, 0.40], "size": [0.02, 1.60, 0.80]},
        POST,
    ],
    "objects": [
        {"name": name, "category": "toys_office", "mesh": f"assets/{name}.ply", "scale": 0.001,
         "pose": {"xyz": list(xyz), "rpy_deg": list(rpy)}} for name, (xyz, rpy) in CUBE_POSES.items()
    ],
    "camera": {"model": "synthetic", "width": 320, "height": 240, "hfov_deg": 70, "depth_min_m": 0.05,
               "depth_max_m": 3.0},
}


def cube_mesh_mm(size: float = CUBE_MM) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """A cube with its bottom face centred at the origin (z up), millimetres, outward triangles."""
    h = size / 2.0
    v = np.array([[x, y, z] for z in (0.0, size) for y in (-h, h) for x in (-h, h)], dtype=np.float64)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = []
    for a, b, c, d in quads:
        faces += [(a, b, c), (a, c, d)]
    return v, np.asarray(faces, dtype=np.int64)


def world_T_cube(name: str) -> NDArray[np.float64]:
    xyz, rpy = CUBE_POSES[name]
    return make_transform(rpy_deg_to_matrix(rpy), xyz)


def true_mesh() -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The scene's true surfaces in metres, world frame: the collision boxes (table, wall, post)
    and the two cubes at their poses."""
    unit, faces = cube_mesh_mm(1.0)
    unit = unit - [0.0, 0.0, 0.5]  # centred
    parts = [(unit * b["size"] + b["center"], faces) for b in SPEC["collision_boxes"]]  # type: ignore[attr-defined]
    v_mm, f = cube_mesh_mm()
    for name in CUBE_POSES:
        T = world_T_cube(name)
        parts.append(((v_mm / 1000.0) @ T[:3, :3].T + T[:3, 3], f))
    vertices, out, n = [], [], 0
    for v, f in parts:
        vertices.append(v)
        out.append(f + n)
        n += len(v)
    return np.concatenate(vertices), np.concatenate(out)


# ----------------------------------------------------------------------------- Gaussians
def _plane_gaussians(origin, u_axis, v_axis, u_len, v_len, spacing, colour_fn, rng, scale_factor=0.9):  # type: ignore[no-untyped-def]
    nu = max(1, round(u_len / spacing))
    nv = max(1, round(v_len / spacing))
    a = (np.arange(nu) + 0.5) / nu * u_len
    b = (np.arange(nv) + 0.5) / nv * v_len
    A, B = np.meshgrid(a, b, indexing="ij")
    A = A.ravel() + rng.normal(0, 0.1 * spacing, A.size)
    B = B.ravel() + rng.normal(0, 0.1 * spacing, B.size)
    u_axis, v_axis = np.asarray(u_axis, float), np.asarray(v_axis, float)
    pts = np.asarray(origin, float) + A[:, None] * u_axis + B[:, None] * v_axis
    normal = np.cross(u_axis, v_axis)
    R = np.stack([u_axis, v_axis, normal], axis=1)
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()  # xyzw
    quats = np.tile(q[[3, 0, 1, 2]], (len(pts), 1))
    s = scale_factor * spacing
    scales = np.tile([s, s, 0.05 * s], (len(pts), 1))
    colours = colour_fn(A, B)
    return pts, quats, scales, colours


def checker(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """The table's colour (25 mm squares) at table coordinates ``A``, ``B`` (metres from its corner)."""
    light = ((np.floor(A / 0.025) + np.floor(B / 0.025)) % 2 == 0)[:, None]
    return np.where(light, [0.9, 0.85, 0.75], [0.35, 0.3, 0.25])


def synthetic_splat(n_gaussians: int = 20_000, sh_degree: int = 0, seed: int = 0,  # type: ignore[no-untyped-def]
                    volume_fraction: float = 0.0):
    """``brave6d.training.ply.SplatData`` of the synthetic scene (about ``n_gaussians``, most on the table).

    ``volume_fraction`` of the budget goes to semi-transparent flat blobs (3-10 mm, opacity
    0.05-0.5) in the top 3 mm of the table around the objects, coloured like the table under
    them: like the fuzzy, overlapping Gaussians of a trained scene they raise the number of
    Gaussians per pixel (the compositing cost) without changing what the image shows.
    Benchmarks use it; tests keep the default 0."""
    from brave6d.training import SH_C0, SplatData

    rng = np.random.default_rng(seed)
    parts = []
    # cubes: 1 mm spacing on every face
    for name in CUBE_POSES:
        T = world_T_cube(name)
        c = np.asarray(CUBE_COLOURS[name])
        h = CUBE_MM / 2000.0
        s = CUBE_MM / 1000.0
        faces = [((-h, -h, s), (1, 0, 0), (0, 1, 0)), ((-h, h, 0), (1, 0, 0), (0, -1, 0)),
                 ((-h, -h, 0), (1, 0, 0), (0, 0, 1)), ((h, h, 0), (-1, 0, 0), (0, 0, 1)),
                 ((-h, h, 0), (0, -1, 0), (0, 0, 1)), ((h, -h, 0), (0, 1, 0), (0, 0, 1))]
        for o, ua, va in faces:
            o_w = T[:3, :3] @ np.asarray(o) + T[:3, 3]
            parts.append(_plane_gaussians(o_w, T[:3, :3] @ np.asarray(ua, float), T[:3, :3] @ np.asarray(va, float),
                                          s, s, 0.0015, lambda A, B, c=c: np.tile(c, (A.size, 1)), rng))
    # post (only its faces towards the room) and wall
    pc, ps = np.asarray(POST["center"]), np.asarray(POST["size"])
    lo = pc - ps / 2
    grey = lambda A, B: np.tile([0.55, 0.55, 0.5], (A.size, 1))
    for o, ua, va, ul, vl in [((lo[0], lo[1], 0.0), (1, 0, 0), (0, 0, 1), ps[0], ps[2]),
                              ((lo[0], lo[1], 0.0), (0, 1, 0), (0, 0, 1), ps[1], ps[2])]:
        parts.append(_plane_gaussians(o, ua, va, ul, vl, 0.006, grey, rng))
    parts.append(_plane_gaussians((0.95, -0.6, 0.0), (0, 1, 0), (0, 0, 1), 1.2, 0.6, 0.02,
                                  lambda A, B: np.stack([0.3 + 0.4 * (np.sin(20 * A) > 0), 0.5 + 0 * A,
                                                         0.6 + 0 * A], 1), rng))
    n_volume = int(max(0.0, min(0.9, volume_fraction)) * n_gaussians)
    if n_volume:  # fuzzy layers over the table, coloured like the table under them
        pts = rng.uniform((0.2, -0.3, 0.0), (0.75, 0.3, 0.003), (n_volume, 3))
        q = np.tile([1.0, 0.0, 0.0, 0.0], (n_volume, 1))
        s = np.exp(rng.uniform(np.log(0.003), np.log(0.010), (n_volume, 1))) * np.array([[1.0, 1.0, 0.15]])
        parts.append((pts, q, s, checker(pts[:, 0] - 0.15, pts[:, 1] + 0.55)))
    used = sum(len(p[0]) for p in parts)
    # table: checkerboard (25 mm squares) with what is left of the budget
    area = 0.8 * 1.1
    spacing = math.sqrt(area / max(1000, n_gaussians - used))
    parts.append(_plane_gaussians((0.15, -0.55, 0.0), (1, 0, 0), (0, 1, 0), 0.8, 1.1, spacing, checker, rng, 1.2))
    pts = np.concatenate([p[0] for p in parts]).astype(np.float32)
    quats = np.concatenate([p[1] for p in parts]).astype(np.float32)
    scales = np.concatenate([p[2] for p in parts])
    colours = np.clip(np.concatenate([p[3] for p in parts]), 0.02, 0.98)
    n = len(pts)
    k = (sh_degree + 1) ** 2 - 1
    shN = (rng.normal(0, 0.02, (n, k, 3)) if k else np.zeros((n, 0, 3))).astype(np.float32)
    opac = rng.uniform(0.75, 0.95, n)
    if n_volume:
        start = sum(len(p[0]) for p in parts[:-2])  # the blobs precede the table
        opac[start:start + n_volume] = rng.uniform(0.05, 0.5, n_volume)
    return SplatData(means=pts, sh0=((colours - 0.5) / SH_C0).reshape(n, 1, 3).astype(np.float32), shN=shN,
                     opacities=np.log(opac / (1 - opac)).astype(np.float32),
                     scales=np.log(np.maximum(scales, 1e-6)).astype(np.float32), quats=quats)


# ----------------------------------------------------------------------------- the scene directory
def ring_poses(n_views: int, distance: float = 0.3, elevation_deg: float = 50.0) -> list[NDArray[np.float64]]:
    el = math.radians(elevation_deg)
    target = np.asarray(TARGET)
    out = []
    for k in range(n_views):
        az = -math.pi / 2 + 2 * math.pi * k / n_views
        eye = target + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        out.append(look_at(eye, target))
    return out


def make_synthetic_scene(root: Path | str, n_gaussians: int = 20_000, sh_degree: int = 0, n_views: int = 10,
                         width: int = 320, height: int = 240, seed: int = 0, volume_fraction: float = 0.0,
                         depth: bool = False, objects: bool = True) -> SceneDir:
    """Write the synthetic scene directory (see the module docstring); returns it. ``objects=False``:
    the cubes stay in the splat but the spec and the annotation list none, as an imported capture
    nobody has annotated yet (its bundle serves free views only)."""
    from brave6d.annotation import write_ply_mesh
    from brave6d.training import holdout_split, write_holdout, write_ply

    scene = SceneDir(root)
    scene.root.mkdir(parents=True, exist_ok=True)
    v, f = cube_mesh_mm()
    for name in CUBE_POSES:
        write_ply_mesh(scene.asset_path(f"{name}.ply"), v, f)
    spec = json.loads(json.dumps(SPEC))
    spec["camera"].update({"width": width, "height": height})
    spec["capture"]["depth"] = depth
    if not objects:
        del spec["objects"]
    import yaml

    scene.spec_path.write_text(yaml.safe_dump(spec, sort_keys=False), encoding="utf-8")
    scene.load_spec()  # validates
    camera = PinholeCamera.from_hfov(width, height, 70.0)
    write_intrinsics(scene, camera, method="synthetic")
    write_handeye(scene, np.eye(4), method="synthetic")
    frames = FrameLog(scene.frames_path)
    if scene.frames_path.exists():
        scene.frames_path.unlink()
    grey = np.full((height, width, 3), 128, dtype=np.uint8)
    truth = None
    if depth:
        from brave6d.core.atomic import depth_m_to_mm_u16
        from brave6d.serve.reference import ReferenceGeometry

        truth = ReferenceGeometry(*true_mesh())
    for k, T in enumerate(ring_poses(n_views)):
        rgb = f"rgb/{k:06d}.png"
        write_png(scene.capture.file(rgb), grey)
        depth_file = None
        if truth is not None:
            depth_file = f"depth/{k:06d}.png"
            write_png(scene.capture.file(depth_file), depth_m_to_mm_u16(truth.depth(T, camera)))
        frames.append(FrameRecord(index=k, view_id=f"d0_v{k:03d}", distance_level=0, distance_m=0.3, rgb=rgb,
                                  depth=depth_file, base_T_tcp=T.tolist(), joints=[0.0] * 6, timestamp=float(k)))
    write_ply(scene.splat_ply_path, synthetic_splat(n_gaussians, sh_degree, seed, volume_fraction))
    records = scene.frames()
    _, held_out = holdout_split(records)
    write_holdout(scene, [r for r in records if r.index in held_out])  # as training records its split
    from brave6d.annotation import AnnotatedInstance, AnnotatedObject, Annotation, write_annotation

    if not objects:
        write_annotation(scene, Annotation((), (), {}, source={"kind": "none", "note": "no objects annotated yet"}))
        return scene

    meshes = scene.annotation_meshes_dir
    objects, instances, id_map = [], [], {}
    for obj_id, name in enumerate(CUBE_POSES, start=1):
        write_ply_mesh(meshes / f"{name}.ply", v, f)
        objects.append(AnnotatedObject(obj_id, name, name, meshes / f"{name}.ply", 0.001,
                                       class_name="toys_office", description="20 mm cube"))
        instances.append(AnnotatedInstance(obj_id, name, world_T_cube(name), entry=0))
        id_map[name] = obj_id
    write_annotation(scene, Annotation(tuple(objects), tuple(instances), id_map, {"synthetic": True}, {}))
    return scene


def make_synthetic_bundle(root: Path | str, n_gaussians: int = 20_000, sh_degree: int = 0, n_views: int = 10,
                          width: int = 320, height: int = 240, bop: bool = False, seed: int = 0,
                          volume_fraction: float = 0.0, depth: bool = False, objects: bool = True) -> Path:
    """The synthetic scene under ``root`` and its bundle (``root/bundle``); ``bop`` also runs the
    annotation stage's BOP export first (so the bundle takes BOP's models); ``depth``: the capture
    records true depth, so the bundle has a reference geometry; ``objects=False``: a bundle without
    objects (:func:`make_synthetic_scene`)."""
    from brave6d.serve.bundle import export_bundle

    scene = make_synthetic_scene(root, n_gaussians, sh_degree, n_views, width, height, seed, volume_fraction, depth,
                                 objects)
    if bop:
        from brave6d.annotation import export_bop

        export_bop(scene.root)
    return export_bundle(scene.root).root
