"""How this sample was made (run once; the tests never run it).

    python make_sample.py SOURCE_JPG_DIR OUT_DIR [--sfm-size 1068x712] [--size 480x320] [--threads 2]

1. Every source photo (4272x2848 Canon JPEG, EXIF orientation 1, all at 55 mm) is resampled with
   Pillow's area filter (``Image.Resampling.BOX``) to ``--sfm-size`` (for structure from motion)
   and to ``--size`` (what is shipped: JPEG quality 85, no EXIF).
2. pycolmap reconstructs the ``--sfm-size`` photos: SIFT on the CPU (4096 features), exhaustive
   guided matching, incremental mapping with one shared OPENCV camera (fx, fy, cx, cy, k1, k2, p1,
   p2) starting from the focal length the EXIF gives (55 mm at 4720.44 px per inch on the sensor),
   distortion held at zero while mapping (it overfits a two-view start), then one global bundle
   adjustment that refines the focal lengths and the distortion with every image (principal point
   fixed). The largest model is kept; photos it did not register are left out.
3. The model is carried to ``--size`` exactly: a pure scaling by s = size / sfm-size, which in
   COLMAP's pixel convention multiplies fx, fy, cx, cy and every keypoint by s (distortion is in
   normalised coordinates and does not change). Only the keypoints that have a 3D point are kept
   (size). ``sparse/0`` is written in COLMAP's binary format.
4. ``transforms.json`` + ``sparse_pc.ply`` are written from that model the way nerfstudio's
   ``ns-process-data`` (``colmap_to_json``, nerfstudio 1.x) writes them: camera-to-world with the
   OpenCV -> OpenGL column flip, then its world permutation (rows 0, 2, 1, row 2 negated; kept as
   ``applied_transform``), COLMAP's intrinsics copied as they are (pixel centres at +0.5).

Nothing here is BRAVE-6D code: it only uses Pillow, NumPy and pycolmap.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image


def resample(src: Path, out: Path, size: tuple[int, int], quality: int = 95) -> float:
    """Resample the photos into ``out``; returns the focal length prior (px at ``size``) from EXIF."""
    out.mkdir(parents=True, exist_ok=True)
    focals = set()
    for path in sorted(src.glob("*.JPG")):
        with Image.open(path) as im:
            exif = im.getexif().get_ifd(0x8769)
            # FocalLength (mm) x FocalPlaneXResolution (px per inch, unit 2) / 25.4 = px at full size
            focals.add(round(float(exif[0x920A]) * float(exif[0xA20E]) / 25.4 * size[0] / im.width, 6))
            small = im.convert("RGB").resize(size, Image.Resampling.BOX)
        small.save(out / (path.stem + ".jpg"), quality=quality)
    if len(focals) != 1:
        raise SystemExit(f"the photos have different focal lengths: {sorted(focals)}")
    return focals.pop()


def reconstruct(images: Path, work: Path, threads: int, focal: float, size: tuple[int, int]) -> pycolmap.Reconstruction:
    db = work / "database.db"
    prior = [focal, focal, size[0] / 2, size[1] / 2, 0.0, 0.0, 0.0, 0.0]  # COLMAP's pixel convention
    reader = pycolmap.ImageReaderOptions(camera_model="OPENCV", camera_params=",".join(repr(v) for v in prior))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = 4096
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.guided_matching = True
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.ba_refine_extra_params = False
    models = pycolmap.incremental_mapping(db, images, work / "sparse", options=options)
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_extra_params = True
    ba.refine_focal_length = True
    ba.refine_principal_point = False
    pycolmap.bundle_adjustment(rec, ba)
    return rec


def rescaled(rec: pycolmap.Reconstruction, s: float) -> pycolmap.Reconstruction:
    """The model for images scaled by ``s``, with only the keypoints that have a 3D point."""
    out = pycolmap.Reconstruction()
    for cam in rec.cameras.values():
        params = np.array(cam.params, dtype=np.float64)
        params[:4] *= s  # OPENCV: fx, fy, cx, cy scale; k1, k2, p1, p2 do not
        out.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model.name, width=round(cam.width * s),
                                                        height=round(cam.height * s), params=params.tolist(),
                                                        camera_id=cam.camera_id))
    index: dict[tuple[int, int], int] = {}
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.images[image_id]
        kept = [(i, p) for i, p in enumerate(image.points2D) if p.has_point3D()]
        points2D = [pycolmap.Point2D(xy=np.asarray(p.xy) * s) for _, p in kept]
        for new, (old, _) in enumerate(kept):
            index[(image_id, old)] = new
        out.add_image_with_trivial_frame(pycolmap.Image(name=image.name, points2D=points2D, camera_id=image.camera_id,
                                                        image_id=image_id), image.cam_from_world())
    for point_id in sorted(rec.point3D_ids()):
        point = rec.points3D[point_id]
        track = pycolmap.Track()
        for element in point.track.elements:
            track.add_element(element.image_id, index[(element.image_id, element.point2D_idx)])
        out.add_point3D(point.xyz, track, point.color)
    return out


def nerfstudio_transforms(rec: pycolmap.Reconstruction) -> tuple[dict, np.ndarray, np.ndarray]:
    (camera,) = rec.cameras.values()
    fx, fy, cx, cy, k1, k2, p1, p2 = (float(v) for v in camera.params)
    frames = []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.images[image_id]
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()
        c2w = np.linalg.inv(w2c)
        c2w[0:3, 1:3] *= -1
        c2w = c2w[np.array([0, 2, 1, 3]), :]
        c2w[2, :] *= -1
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": c2w.tolist(), "colmap_im_id": image_id})
    applied = np.eye(4)[:3, :]
    applied = applied[np.array([0, 2, 1]), :]
    applied[2, :] *= -1
    out = {"w": camera.width, "h": camera.height, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
           "k1": k1, "k2": k2, "p1": p1, "p2": p2, "camera_model": "OPENCV", "frames": frames,
           "applied_transform": applied.tolist(), "ply_file_path": "sparse_pc.ply"}
    ids = sorted(rec.point3D_ids())
    xyz = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids], np.uint8).reshape(-1, 3)
    return out, xyz @ applied[:3, :3].T + applied[:3, 3], rgb


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    header = ("ply\nformat ascii 1.0\n"
              f"element vertex {len(xyz)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uint8 red\nproperty uint8 green\nproperty uint8 blue\nend_header\n")
    rows = "".join(f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]}\n" for p, c in zip(xyz, rgb))
    path.write_text(header + rows)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("source", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--sfm-size", default="1068x712")
    parser.add_argument("--size", default="480x320")
    parser.add_argument("--quality", type=int, default=85)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    sfm_size = tuple(int(v) for v in args.sfm_size.split("x"))
    size = tuple(int(v) for v in args.size.split("x"))
    s = size[0] / sfm_size[0]
    if abs(size[1] / sfm_size[1] - s) > 1e-9:
        raise SystemExit("--size and --sfm-size must have the same aspect ratio")
    images = args.out / "images"
    with tempfile.TemporaryDirectory() as tmp:
        big = Path(tmp) / "images"
        focal = resample(args.source, big, sfm_size)  # type: ignore[arg-type]
        resample(args.source, images, size, args.quality)  # type: ignore[arg-type]
        print(f"focal length prior from EXIF: {focal:.1f} px at {args.sfm_size}")
        rec = rescaled(reconstruct(big, Path(tmp), args.threads, focal, sfm_size), s)  # type: ignore[arg-type]
    registered = {rec.images[i].name for i in rec.reg_image_ids()}
    for path in images.iterdir():
        if path.name not in registered:
            print(f"left out (not registered): {path.name}")
            path.unlink()
    sparse = args.out / "sparse" / "0"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir(parents=True)
    rec.write_binary(str(sparse))
    transforms, xyz, rgb = nerfstudio_transforms(rec)
    (args.out / "transforms.json").write_text(json.dumps(transforms, indent=1))
    write_ply(args.out / "sparse_pc.ply", xyz, rgb)
    print(rec.summary())


if __name__ == "__main__":
    main()
