"""The project's trainer against OpenSplat on a real COLMAP sample: same photos, split and steps.

OpenSplat (https://github.com/pierotofy/OpenSplat, C++/libtorch) reads a COLMAP model directly.
For a sample (``skull`` or ``fox`` from ``tests/data/real``, or any folder with ``sparse/0`` and
``images``) this script

1. imports the model with ``brave6d import`` (the sample's scale pair, ``--up auto``) and computes
   the project's holdout split (:func:`brave6d.training.holdout.holdout_split`: 10% of the views,
   evenly spaced in capture order);
2. trains the project (``brave6d train --preset fast --steps N --device cpu``) and reads its holdout
   PSNR from ``splat/metrics.json`` (checking that ``splat/holdout.json`` is the predicted split);
3. writes a COLMAP workspace for OpenSplat without the held-out photos (``images.bin`` without them,
   ``points3D.bin`` with all the model's points, like the project's fallback to the imported
   points, or with ``--points train`` those two or more training photos observe), runs ``opensplat WS -n N -d D --keep-crs
   --cpu`` (``--keep-crs``: the PLY is written in the COLMAP world) with the fast preset's schedule
   in OpenSplat's options (:func:`opensplat_options`; ``--opensplat-schedule defaults``: OpenSplat's
   own, tuned for 30k steps);
4. scores OpenSplat's PLY on the held-out photos exactly as OpenSplat prepares and renders its own
   images: the photo through OpenCV as OpenSplat 1.1.5 does (resize by 1/D with INTER_AREA,
   ``getOptimalNewCameraMatrix`` with alpha 0 *as OpenCV 4.6 computes it* (:func:`opencv46_new_camera_matrix`;
   the pip OpenCV here, 4.14, samples the border differently and gives a focal length 0.4-0.6% longer),
   ``undistort``, ROI crop), the PLY rendered by :func:`opensplat_cpu_render`, a port of OpenSplat's
   CPU forward pass (``--cpu``: ``rasterizer/gsplat-cpu/gsplat_cpu.cpp``), not by the project's
   rasterizer. The port is needed because OpenSplat's CPU rasterizer does not composite in depth
   order: it sorts the Gaussians by ``camDepths.data_ptr()`` of a stride-3 view (``pProj[..., 2]``),
   so the key of Gaussian ``i`` is element ``i + 2`` of the flattened ``[N, 3]`` NDC positions (a mix
   of other Gaussians' x, y and z); the model is trained through that order, and a depth-sorted
   render of its PLY (any standard 3DGS renderer, the project's included) is a different image
   (about 13 dB PSNR from OpenSplat's own on skull). The port's other conventions are OpenSplat's
   too: principal point at the image centre (``cx, cy`` are not used; pixel ``j`` at ``fx x/z + W/2
   - 0.5``), per-axis 3-sigma boxes, no near-plane cull, its fixed background colour, the SH degree it
   had reached, output clamped at 1. Check: the middle held-out photo is left in OpenSplat's input
   and withheld by its own ``--val``; ``--val-render`` writes OpenSplat's own render of it, and
   :func:`check_against_own_render` compares it with the port's (``val_check`` in the JSON; the
   multi-view figure is flagged invalid below :data:`VAL_CHECK_MIN_PSNR`).
   ``holdout_psnr_depth_sorted``: the same PLY rendered by the project's rasterizer in depth order
   (what a viewer of the PLY shows), for reference.

Both figures are the mean PSNR over the same held-out photos, each tool at its own preparation of
those photos at the same downscale (the project's images are undistorted once at full size, then
resampled, so the two ground truths differ by resampling only). It prints one JSON object: holdout
PSNR of each, the number of views each rests on, wall times. ``--score-only PLY`` rescores an
existing OpenSplat PLY (no training; the split is read from ``--work``'s imported scene).

    python benchmarks/opensplat_compare.py --opensplat /path/to/opensplat --sample skull [--steps 2000]
        [--work /tmp/osc-skull] [--json out.json] [--opensplat-schedule fast|defaults] [--skip-project]
    python benchmarks/opensplat_compare.py --opensplat /path/to/opensplat --sample skull --work /tmp/osc-skull \
        --score-only /tmp/osc-skull/opensplat/splat.ply
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO / "src") not in sys.path:  # the package, also without an install
    sys.path.insert(0, str(REPO / "src"))

#: The shipped real samples: folder and the scale pair of their README/tests (photo A, photo B, metres).
SAMPLES: dict[str, tuple[Path, tuple[str, str]]] = {
    "skull": (REPO / "tests" / "data" / "real" / "skull", ("01.jpg", "30.jpg")),
    "fox": (REPO / "tests" / "data" / "real" / "fox", ("0001.jpg", "0110.jpg")),
}
#: OpenSplat's background colour (model.hpp: nerfstudio's default, not optimised, not in the PLY).
OPENSPLAT_BACKGROUND = (0.6130, 0.0101, 0.3984)
#: OpenSplat's step-counted options and their defaults (opensplat.cpp), for a 30k-step run.
OPENSPLAT_STEP_OPTIONS = {"resolution-schedule": 3000, "sh-degree-interval": 1000, "refine-every": 100,
                          "warmup-length": 500, "stop-screen-size-at": 4000}
OPENSPLAT_DEFAULT_STEPS = 30_000
#: Agreement (PSNR) of this script's render of OpenSplat's PLY with OpenSplat's own render of the --val view
#: below which the script's multi-view figure is flagged as not OpenSplat's.
VAL_CHECK_MIN_PSNR = 35.0
#: The project's command line, next to this interpreter (the venv's console script).
BRAVE6D = str(Path(sys.executable).parent / "brave6d")


# ----------------------------------------------------------------------------- COLMAP binary files
def _read_images_bin(path: Path) -> list[dict[str, Any]]:
    data = path.read_bytes()
    (n,), off = struct.unpack_from("<Q", data, 0), 8
    out = []
    for _ in range(n):
        start = off
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = struct.unpack_from("<I7dI", data, off)
        off += struct.calcsize("<I7dI")
        end = data.index(b"\0", off)
        name = data[off:end].decode()
        off = end + 1
        (npts,) = struct.unpack_from("<Q", data, off)
        off += 8 + npts * 24
        out.append({"id": image_id, "q": (qw, qx, qy, qz), "t": (tx, ty, tz), "camera_id": cam_id,
                    "name": name, "raw": data[start:off]})
    return out


def _filter_points3d(src: Path, dst: Path, train_ids: set[int], min_views: int = 2) -> tuple[int, int]:
    """Copy ``points3D.bin`` keeping the points at least ``min_views`` training images observe; the
    kept points keep their whole track (OpenSplat reads only position and colour)."""
    data = src.read_bytes()
    (n,), off = struct.unpack_from("<Q", data, 0), 8
    kept: list[bytes] = []
    head = struct.calcsize("<Q3d3BdQ")
    for _ in range(n):
        start = off
        *_, track_len = struct.unpack_from("<Q3d3BdQ", data, off)
        off += head
        ids = struct.unpack_from(f"<{2 * track_len}I", data, off)[0::2]
        off += 8 * track_len
        if len({i for i in ids if i in train_ids}) >= min_views:
            kept.append(data[start:off])
    dst.write_bytes(struct.pack("<Q", len(kept)) + b"".join(kept))
    return len(kept), n


def _read_cameras_bin(path: Path) -> dict[int, dict[str, Any]]:
    n_params = {0: 3, 1: 4, 2: 4, 4: 8}  # SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, OPENCV (what OpenSplat reads)
    data = path.read_bytes()
    (n,), off = struct.unpack_from("<Q", data, 0), 8
    cams = {}
    for _ in range(n):
        cam_id, model, w, h = struct.unpack_from("<IiQQ", data, off)
        off += struct.calcsize("<IiQQ")
        if model not in n_params:
            raise SystemExit(f"{path}: camera model {model} is not one OpenSplat reads")
        params = struct.unpack_from(f"<{n_params[model]}d", data, off)
        off += 8 * n_params[model]
        fx, fy, cx, cy, dist = _intrinsics(model, params)
        cams[cam_id] = {"width": w, "height": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy, "dist": dist}
    return cams


def _intrinsics(model: int, p: tuple[float, ...]) -> tuple[float, float, float, float, list[float]]:
    if model == 0:
        return p[0], p[0], p[1], p[2], [0.0] * 4
    if model == 1:
        return p[0], p[1], p[2], p[3], [0.0] * 4
    if model == 2:
        return p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0]
    return p[0], p[1], p[2], p[3], list(p[4:8])  # k1 k2 p1 p2


def _quat_to_rot(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ----------------------------------------------------------------------------- the project
def _run(cmd: list[str], log: Path) -> float:
    t0 = time.perf_counter()
    with log.open("w") as fh:
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({rc}); see {log}")
    return time.perf_counter() - t0


def import_scene(sample: Path, pair: tuple[str, str], scene: Path, work: Path) -> None:
    if scene.exists():
        shutil.rmtree(scene)
    _run([BRAVE6D, "import", str(sample / "sparse" / "0"), str(scene), "--images",
          str(sample / "images"), "--scale-from-distance", pair[0], pair[1], "1.0", "--up", "auto"],
         work / "import.log")


def predicted_holdout(scene: Path) -> list[tuple[int, str, str]]:
    """``(index, view_id, source image)`` of the views the project's rule holds out of ``scene``."""
    from brave6d.training.holdout import holdout_split

    class _Rec:
        def __init__(self, d: dict[str, Any]) -> None:
            self.index, self.distance_level = d["index"], d["distance_level"]

    rows = [json.loads(line) for line in (scene / "capture" / "frames.jsonl").read_text().splitlines() if line.strip()]
    _, test = holdout_split([_Rec(r) for r in rows])  # type: ignore[arg-type]
    by_index = {r["index"]: r for r in rows}
    return [(i, by_index[i]["view_id"], by_index[i]["source_image"]) for i in test]


def train_project(scene: Path, steps: int, work: Path) -> dict[str, Any]:
    wall = _run([BRAVE6D, "train", str(scene), "--preset", "fast", "--steps", str(steps),
                 "--device", "cpu"], work / "project_train.log")
    m = json.loads((scene / "splat" / "metrics.json").read_text())
    held = json.loads((scene / "splat" / "holdout.json").read_text())
    return {"holdout_psnr": m["holdout"]["psnr"], "holdout_ssim": m["holdout"]["ssim"],
            "n_holdout_views": m["holdout"]["n_views"], "holdout_view_ids": [v["view_id"] for v in held["views"]],
            "steps": m["steps"], "stopped_by": m["stopped_by"], "train_time_s": m["train_time_s"],
            "wall_s": wall, "num_gaussians": m["num_gaussians"],
            "resolution": m["images"]["metrics_resolution"], "init": m.get("init")}


# ----------------------------------------------------------------------------- OpenSplat
def write_workspace(sample: Path, ws: Path, held_names: set[str], points: str = "all",
                    val_name: str | None = None) -> dict[str, Any]:
    """A COLMAP workspace for OpenSplat: the sample's model without the held-out photos; ``points``:
    ``all`` (the model's points, as the project's fallback to the imported points) or ``train``
    (those two or more training photos observe). ``val_name``: one held-out photo left in, for
    OpenSplat's own ``--val`` (it withholds it from training and renders it)."""
    if ws.exists():
        shutil.rmtree(ws)
    model = ws / "sparse" / "0"
    model.mkdir(parents=True)
    src = sample / "sparse" / "0"
    shutil.copy(src / "cameras.bin", model / "cameras.bin")
    images = _read_images_bin(src / "images.bin")
    missing = held_names - {im["name"] for im in images}
    if missing:
        raise SystemExit(f"held-out photos not in {src}/images.bin: {sorted(missing)}")
    train = [im for im in images if im["name"] not in held_names]
    listed = [im for im in images if im["name"] not in held_names or im["name"] == val_name]
    (model / "images.bin").write_bytes(struct.pack("<Q", len(listed)) + b"".join(im["raw"] for im in listed))
    kept, total = _filter_points3d(src / "points3D.bin", model / "points3D.bin", {im["id"] for im in train},
                                   min_views=2 if points == "train" else 0)
    os.symlink((sample / "images").resolve(), ws / "images")
    return {"train_images": len(train), "points_kept": kept, "points_total": total}


def opensplat_options(steps: int, schedule: str) -> dict[str, int]:
    """OpenSplat's step-counted options for an ``steps``-step run.

    ``fast`` (default): the project's ``fast`` schedule in OpenSplat's terms, as fractions of the run
    (fast: 2000 steps, the first 600 at half resolution, SH degree +1 every 400, densify every 50 from
    step 100, no opacity reset): ``--num-downscales 1 --resolution-schedule 0.3N --sh-degree-interval
    0.2N --refine-every N/40 --warmup-length N/20 --reset-alpha-every 1000000`` and
    ``--stop-screen-size-at`` scaled from its 4000 of 30k. OpenSplat's defaults are for 30k steps and
    do not shrink proportionally: densification waits for ``step % (reset-alpha-every * refine-every) >
    cameras + refine-every``, which a proportionally shrunk ``refine-every`` never reaches, and at
    its default ``--resolution-schedule 3000`` a short run trains on quarter-size images throughout.
    OpenSplat stops densifying at half the run (fixed in its code; the fast preset at 60%).
    ``defaults``: none given (OpenSplat as shipped)."""
    if schedule == "defaults":
        return {}
    return {"num-downscales": 1, "resolution-schedule": max(1, round(0.3 * steps)),
            "sh-degree-interval": max(1, round(0.2 * steps)), "refine-every": max(1, round(steps / 40)),
            "warmup-length": max(1, round(steps / 20)), "reset-alpha-every": 1_000_000,
            "stop-screen-size-at": max(1, round(4000 * steps / OPENSPLAT_DEFAULT_STEPS))}


def train_opensplat(binary: Path, ws: Path, out: Path, steps: int, downscale: int, options: dict[str, int],
                    work: Path, val_name: str | None = None) -> dict[str, Any]:
    cmd = [str(binary), str(ws), "-n", str(steps), "-d", str(downscale), "--keep-crs", "--cpu", "-o", str(out)]
    if val_name is not None:  # OpenSplat's own render of one held-out view, every 10 steps
        cmd += ["--val", "--val-image", val_name, "--val-render", str(out.parent / "val_render")]
    for k, v in options.items():
        cmd += [f"--{k}", str(v)]
    wall = _run(cmd, work / "opensplat_train.log")
    lines = (work / "opensplat_train.log").read_text().splitlines()
    val = [ln for ln in lines if "validation loss" in ln]
    return {"command": " ".join(cmd), "wall_s": wall, "own_validation_line": val[-1] if val else None}


def check_against_own_render(ours_png: Path, own_png: Path) -> dict[str, Any]:
    """PSNR of this script's render of the ``--val`` view against OpenSplat's own render of it (the
    left half of our side-by-side PNG against ``val_render/<steps>.png``), and of OpenSplat's own
    render against the ground truth (the right half): how far this script's scoring is from OpenSplat's."""
    import cv2

    side = cv2.imread(str(ours_png)).astype(np.float64)
    own = cv2.imread(str(own_png)).astype(np.float64)
    w = own.shape[1]
    ours, gt = side[:, :w], side[:, w:]

    def _psnr(a: np.ndarray, b: np.ndarray) -> float:
        return -10.0 * math.log10(max(float(np.mean((a / 255.0 - b / 255.0) ** 2)), 1e-12))
    return {"ours_vs_own_render_psnr": _psnr(ours, own),
            "ours_vs_own_render_max_abs_diff": int(np.abs(ours - own).max()),
            "own_render_vs_gt_psnr": _psnr(own, gt), "ours_vs_gt_psnr": _psnr(ours, gt)}


def opencv46_new_camera_matrix(K: np.ndarray, dist: np.ndarray, width: int, height: int
                               ) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """``cv2.getOptimalNewCameraMatrix(K, dist, (width, height), 0)`` as OpenCV 4.6 (OpenSplat's,
    Debian 12) computes it: the inscribed rectangle of 9x9 undistorted points ``x * width / 8``
    (later OpenCV samples ``x * (width - 1) / 8``), mapped onto ``width - 1`` by ``height - 1``.
    Returns the new K (float32, OpenCV's pixel centres) and the valid-pixel ROI ``(x, y, w, h)``."""
    import cv2

    n = 9
    pts = np.array([[x * width / (n - 1), y * height / (n - 1)] for y in range(n) for x in range(n)],
                   np.float32).reshape(-1, 1, 2)
    u = cv2.undistortPoints(pts, K.astype(np.float32), dist.astype(np.float32)).reshape(n, n, 2).astype(np.float64)
    x0, x1 = float(u[:, 0, 0].max()), float(u[:, n - 1, 0].min())
    y0, y1 = float(u[0, :, 1].max()), float(u[n - 1, :, 1].min())
    fx, fy = (width - 1) / (x1 - x0), (height - 1) / (y1 - y0)
    new_k = np.array([[fx, 0.0, -fx * x0], [0.0, fy, -fy * y0], [0.0, 0.0, 1.0]], np.float32)
    # the inscribed rectangle maps onto (0, 0, width - 1, height - 1): OpenCV's ceil/floor of that
    roi = (0, 0, int(math.floor((x1 - x0) * fx + 1e-3)), int(math.floor((y1 - y0) * fy + 1e-3)))
    return new_k, roi


def prepare_like_opensplat(path: Path, cam: dict[str, Any], downscale: int
                           ) -> tuple[np.ndarray, float, float]:
    """The photo as OpenSplat 1.1.5's ``Camera::loadImage`` prepares it (RGB uint8) and the focal
    lengths it then renders with."""
    import cv2

    img = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    fx, fy, cx, cy = (np.float32(cam[k]) for k in ("fx", "fy", "cx", "cy"))  # OpenSplat's floats
    if img.shape[0] != cam["height"] or img.shape[1] != cam["width"]:
        r = np.float32(img.shape[0]) / np.float32(cam["height"])
        fx, fy, cx, cy = fx * r, fy * r, cx * r, cy * r
    if downscale > 1:
        img = cv2.resize(img, None, fx=1.0 / downscale, fy=1.0 / downscale, interpolation=cv2.INTER_AREA)
        f = np.float32(1.0 / downscale)
        fx, fy, cx, cy = fx * f, fy * f, cx * f, cy * f
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float32)
    dist = np.array(cam["dist"] + [0.0, 0.0, 0.0, 0.0], np.float32)  # k1 k2 p1 p2 k3(0) k4 k5 k6 as OpenSplat
    if np.any(dist != 0):
        new_k, (x, y, w, h) = opencv46_new_camera_matrix(K, dist, img.shape[1], img.shape[0])
        img = cv2.undistort(img, K, dist, None, new_k)[y:y + h, x:x + w]
        K = new_k
    return np.ascontiguousarray(img), float(K[0, 0]), float(K[1, 1])


_OS_RASTER = None


def _os_raster_kernel() -> Any:
    """OpenSplat's ``rasterize_forward_tensor_cpu`` compiled with Numba (float32, same loop order)."""
    global _OS_RASTER
    if _OS_RASTER is None:
        import numba

        @numba.njit(cache=False)
        def raster(order, xys, conics, sqx_a, sqy_a, colors, opac, bgc, height, width):  # pragma: no cover
            out = np.zeros((height, width, 3), np.float32)
            ts = np.ones((height, width), np.float32)
            done = np.zeros((height, width), np.bool_)
            for gid in order:
                a, b, c = conics[gid, 0], conics[gid, 1], conics[gid, 2]
                gx, gy, sqx, sqy = xys[gid, 0], xys[gid, 1], sqx_a[gid], sqy_a[gid]
                if not (np.isfinite(gx) and np.isfinite(gy) and np.isfinite(sqx) and np.isfinite(sqy)):
                    continue
                if abs(gx) + sqx > 1e9 or abs(gy) + sqy > 1e9:  # far off screen (behind the camera)
                    continue
                r0 = max(0, int(math.floor(gy - sqy)) - 2)
                r1 = min(height, int(math.ceil(gy + sqy)) + 2)
                c0 = max(0, int(math.floor(gx - sqx)) - 2)
                c1 = min(width, int(math.ceil(gx + sqx)) + 2)
                for i in range(r0, r1):
                    for j in range(c0, c1):
                        if done[i, j]:
                            continue
                        xc = np.float32(gx - j)
                        yc = np.float32(gy - i)
                        sigma = np.float32(0.5) * (a * xc * xc + c * yc * yc) + b * xc * yc
                        if sigma < 0:
                            continue
                        alpha = min(np.float32(0.999), opac[gid] * np.float32(math.exp(-sigma)))
                        if alpha < np.float32(1.0 / 255.0):
                            continue
                        t = ts[i, j]
                        nt = t * (np.float32(1.0) - alpha)
                        if nt <= np.float32(1e-4):
                            done[i, j] = True
                            continue
                        vis = alpha * t
                        for k in range(3):
                            out[i, j, k] += vis * colors[gid, k]
                        ts[i, j] = nt
            for i in range(height):
                for j in range(width):
                    for k in range(3):
                        out[i, j, k] += ts[i, j] * bgc[k]
            return out
        _OS_RASTER = raster
    return _OS_RASTER


_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
          1.445305721320277, -0.5900435899266435)


def opensplat_cpu_render(means: Any, quats: Any, log_scales: Any, logit_opacities: Any, sh: Any, degree: int,
                         viewmat: np.ndarray, fx: float, fy: float, width: int, height: int,
                         background: tuple[float, float, float] = OPENSPLAT_BACKGROUND,
                         depth_order: bool = False) -> np.ndarray:
    """OpenSplat 1.1.5's ``Model::forward`` on the CPU at full scale (``project_gaussians_forward_tensor_cpu``,
    ``compute_sh_forward_tensor_cpu``, ``rasterize_forward_tensor_cpu``), float32: an ``[H, W, 3]`` image.

    ``means`` etc. are torch tensors in the frame of ``viewmat`` (world-to-camera, OpenCV axes); OpenSplat
    trains in a frame scaled and shifted from COLMAP's, which changes no image. Its conventions: the
    projection through a symmetric OpenGL frustum (principal point at the centre, ``cx, cy`` unused),
    pixel ``j`` centred at integer ``j``, per-axis 3-sigma boxes, no near-plane cull, and the compositing
    order of its ``std::sort`` over ``camDepths.data_ptr()``: ``camDepths`` is ``pProj[..., 2]``, a
    stride-3 view, read with stride 1, so Gaussian ``i``'s key is element ``i + 2`` of the flattened
    ``[N, 3]`` NDC positions. ``depth_order=True`` sorts by the true depth instead (for comparison)."""
    import torch

    t = torch
    with t.no_grad():
        vm = t.from_numpy(np.asarray(viewmat, np.float32))
        rc, tc = vm[:3, :3], vm[:3, 3]
        m = means.float()
        s = t.exp(log_scales.float())
        q = quats.float() / quats.float().norm(dim=-1, keepdim=True)
        p_view = (rc @ m[..., None])[..., 0] + tc
        w_, x_, y_, z_ = q.unbind(-1)
        rot = t.stack([t.stack([1 - 2 * (y_ ** 2 + z_ ** 2), 2 * (x_ * y_ - w_ * z_), 2 * (x_ * z_ + w_ * y_)], -1),
                       t.stack([2 * (x_ * y_ + w_ * z_), 1 - 2 * (x_ ** 2 + z_ ** 2), 2 * (y_ * z_ - w_ * x_)], -1),
                       t.stack([2 * (x_ * z_ - w_ * y_), 2 * (y_ * z_ + w_ * x_), 1 - 2 * (x_ ** 2 + y_ ** 2)], -1)],
                      -2)
        mm = rot * s[..., None, :]
        cov3d = mm @ mm.transpose(-1, -2)
        lim_x, lim_y = 1.3 * (0.5 * width / fx), 1.3 * (0.5 * height / fy)
        z = p_view[..., 2]
        tx = z * t.clamp(p_view[..., 0] / z, -lim_x, lim_x)
        ty = z * t.clamp(p_view[..., 1] / z, -lim_y, lim_y)
        rz = 1.0 / z
        rz2 = rz ** 2
        zero = t.zeros_like(rz)
        jac = t.stack([t.stack([fx * rz, zero, -fx * tx * rz2], -1), t.stack([zero, fy * rz, -fy * ty * rz2], -1)], -2)
        tm = jac @ rc
        cov2d = tm @ cov3d @ tm.transpose(-1, -2)
        cov2d[..., 0, 0] += 0.3
        cov2d[..., 1, 1] += 0.3
        det = (cov2d[..., 0, 0] * cov2d[..., 1, 1] - cov2d[..., 0, 1] ** 2).clamp_min(1e-6)
        conic = t.stack([cov2d[..., 1, 1] / det, -cov2d[..., 0, 1] / det, cov2d[..., 0, 0] / det], -1)
        fov_x, fov_y = 2 * math.atan(width / (2 * fx)), 2 * math.atan(height / (2 * fy))
        near, far = 0.001, 1000.0
        proj = t.tensor([[1 / math.tan(0.5 * fov_x), 0, 0, 0], [0, 1 / math.tan(0.5 * fov_y), 0, 0],
                         [0, 0, (far + near) / (far - near), -far * near / (far - near)], [0, 0, 1, 0]],
                        dtype=t.float32)
        p_hom = ((proj @ vm) @ t.cat([m, t.ones_like(m[:, :1])], -1)[..., None])[..., 0]
        p_proj = p_hom[:, :3] * (1.0 / p_hom[:, 3].clamp_min(1e-6))[:, None]
        u = 0.5 * ((p_proj[:, 0] + 1) * width - 1)
        v = 0.5 * ((p_proj[:, 1] + 1) * height - 1)
        # SH colours from the camera centre towards each mean, degreesToUse, +0.5, clamped at 0
        d = m - (-(rc.T @ tc))
        d = d / d.norm(dim=-1, keepdim=True)
        x, y, zz_ = d.unbind(-1)
        basis = [t.full_like(x, 0.28209479177387814)]
        if degree >= 1:
            c1 = 0.4886025119029199
            basis += [c1 * -y, c1 * zz_, c1 * -x]
        if degree >= 2:
            xx, yy, zz, xy, yz, xz = x * x, y * y, zz_ * zz_, x * y, y * zz_, x * zz_
            basis += [_SH_C2[0] * xy, _SH_C2[1] * yz, _SH_C2[2] * (2 * zz - xx - yy), _SH_C2[3] * xz,
                      _SH_C2[4] * (xx - yy)]
        if degree >= 3:
            basis += [_SH_C3[0] * y * (3 * xx - yy), _SH_C3[1] * xy * zz_, _SH_C3[2] * y * (4 * zz - xx - yy),
                      _SH_C3[3] * zz_ * (2 * zz - 3 * xx - 3 * yy), _SH_C3[4] * x * (4 * zz - xx - yy),
                      _SH_C3[5] * zz_ * (xx - yy), _SH_C3[6] * x * (xx - 3 * yy)]
        b = t.stack(basis, -1)
        rgb = ((b[..., None] * sh.float()[:, : b.shape[1]]).sum(-2) + 0.5).clamp_min(0.0)
        key = p_proj[:, 2] if depth_order else p_proj.contiguous().reshape(-1)[2:2 + m.shape[0]]
        order = np.argsort(key.numpy(), kind="stable").astype(np.int64)
        img = _os_raster_kernel()(
            order, t.stack([u, v], -1).numpy().astype(np.float32), conic.numpy().astype(np.float32),
            (3 * cov2d[..., 0, 0].sqrt()).numpy().astype(np.float32),
            (3 * cov2d[..., 1, 1].sqrt()).numpy().astype(np.float32), rgb.numpy().astype(np.float32),
            t.sigmoid(logit_opacities.float()).reshape(-1).numpy().astype(np.float32),
            np.asarray(background, np.float32), height, width)
    return np.minimum(img, np.float32(1.0))


def _to_u8_like_opensplat(img: np.ndarray) -> np.ndarray:
    """OpenSplat's ``tensorToImage``: ``(t * 255).toType(kU8)`` truncates."""
    return (img.astype(np.float32) * np.float32(255.0)).clip(0, 255).astype(np.uint8)


def _psnr_u8(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) / 255.0 - b.astype(np.float64) / 255.0) ** 2))
    return -10.0 * math.log10(max(mse, 1e-12))


def evaluate_opensplat(ply: Path, sample: Path, held_names: list[str], steps: int, downscale: int,
                       sh_interval: int, write_dir: Path | None = None, depth_sorted: bool = True) -> dict[str, Any]:
    """Score OpenSplat's PLY on ``held_names`` with :func:`opensplat_cpu_render` against the photos as
    :func:`prepare_like_opensplat` prepares them (PSNR of the 8-bit images, as OpenSplat would save its
    render); ``depth_sorted``: also the project's rasterizer's depth-ordered render of the same PLY."""
    import cv2
    import torch

    from brave6d.training.ply import read_ply
    from brave6d.training.rasterizer import rasterize

    splat = read_ply(ply)
    src = sample / "sparse" / "0"
    cams = _read_cameras_bin(src / "cameras.bin")
    images = {im["name"]: im for im in _read_images_bin(src / "images.bin")}
    degree = min(steps // sh_interval, splat.sh_degree)  # the degree OpenSplat had reached (step / interval)
    n_sh = (degree + 1) ** 2
    means = torch.from_numpy(splat.means)
    quats = torch.from_numpy(splat.quats)
    log_scales = torch.from_numpy(splat.scales)
    logit_opac = torch.from_numpy(splat.opacities)
    colors = torch.cat([torch.from_numpy(splat.sh0), torch.from_numpy(splat.shN)], dim=1)[:, :n_sh]
    bg = torch.tensor(OPENSPLAT_BACKGROUND, dtype=torch.float32)
    # OpenSplat's own record of the intrinsics it used (written next to the PLY): the check of our OpenCV 4.6 port
    own_cams: dict[str, Any] = {}
    if (ply.parent / "cameras.json").is_file():
        own_cams = {c["img_name"]: c for c in json.loads((ply.parent / "cameras.json").read_text())}
    per_view = []
    for name in held_names:
        im = images[name]
        cam = cams[im["camera_id"]]
        gt, fx, fy = prepare_like_opensplat(sample / "images" / name, cam, downscale)
        h, w = gt.shape[:2]
        same = [c for c in own_cams.values() if images.get(c["img_name"], {}).get("camera_id") == im["camera_id"]]
        if same and (abs(same[0]["fx"] - fx) > 1e-3 * fx or abs(same[0]["fy"] - fy) > 1e-3 * fy
                     or (same[0]["width"], same[0]["height"]) != (w, h)):
            raise SystemExit(f"{name}: intrinsics {fx:.3f} {fy:.3f} {w}x{h}, OpenSplat's cameras.json has "
                             f"{same[0]['fx']:.3f} {same[0]['fy']:.3f} {same[0]['width']}x{same[0]['height']}")
        view = np.eye(4, dtype=np.float32)
        view[:3, :3] = _quat_to_rot(im["q"])
        view[:3, 3] = im["t"]
        render = _to_u8_like_opensplat(opensplat_cpu_render(means, quats, log_scales, logit_opac, colors, degree,
                                                            view, fx, fy, w, h))
        row: dict[str, Any] = {"image": name, "psnr": _psnr_u8(render, gt), "size": f"{w}x{h}"}
        if depth_sorted:  # the project's rasterizer, depth-ordered, OpenSplat's centred principal point
            K = np.array([[fx, 0, w / 2 - 0.5], [0, fy, h / 2 - 0.5], [0, 0, 1]], np.float32)
            rgb, _, _, _ = rasterize(means, quats, torch.exp(log_scales), torch.sigmoid(logit_opac), colors,
                                     torch.from_numpy(view)[None], torch.from_numpy(K)[None], w, h,
                                     sh_degree=degree, backgrounds=bg[None], backend="cpu")
            row["psnr_depth_sorted"] = _psnr_u8(_to_u8_like_opensplat(rgb[0].clamp(0.0, 1.0).numpy()), gt)
        per_view.append(row)
        if write_dir is not None:
            write_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(write_dir / f"{Path(name).stem}.png"),
                        cv2.cvtColor(np.concatenate([render, gt], axis=1), cv2.COLOR_RGB2BGR))
    out = {"holdout_psnr": float(np.mean([v["psnr"] for v in per_view])), "n_holdout_views": len(per_view),
           "renderer": "port of OpenSplat 1.1.5's CPU forward (its compositing order)",
           "sh_degree_rendered": degree, "num_gaussians": splat.num_gaussians, "per_view": per_view}
    if depth_sorted:
        out["holdout_psnr_depth_sorted"] = float(np.mean([v["psnr_depth_sorted"] for v in per_view]))
    return out


def cross_ground_truth(ply: Path, scene: Path, sample: Path, held: list[tuple[int, str, str]], steps: int,
                       downscale: int, sh_interval: int) -> dict[str, Any]:
    """Each tool's model against the *other* tool's preparation of the same held-out photos: the
    project's trained model (``scene/splat/point_cloud.ply``, rendered as its holdout evaluation does)
    in OpenSplat's camera (the alpha-0 new K with its true principal point, ROI size) against the photo
    as OpenSplat prepares it, and OpenSplat's PLY (:func:`opensplat_cpu_render`) in the project's
    camera against the project's image (its valid pixels), beside each tool's own figure."""
    import torch

    from brave6d.core.layout import SceneDir
    from brave6d.training.holdout_eval import render_view
    from brave6d.training.losses import psnr
    from brave6d.training.model import GaussianModel
    from brave6d.training.ply import read_ply
    from brave6d.training.rasterizer import rasterize
    from brave6d.training.views import load_scene

    data = load_scene(SceneDir(scene), downscale=downscale)
    model = GaussianModel.from_ply(scene / "splat" / "point_cloud.ply")
    valid = data.valid_tensor("cpu")
    tests = {v.view_id: v for v in data.test}
    src = sample / "sparse" / "0"
    cams = _read_cameras_bin(src / "cameras.bin")
    images = {im["name"]: im for im in _read_images_bin(src / "images.bin")}
    splat = read_ply(ply)
    degree = min(steps // sh_interval, splat.sh_degree)
    os_args = (torch.from_numpy(splat.means), torch.from_numpy(splat.quats), torch.from_numpy(splat.scales),
               torch.from_numpy(splat.opacities),
               torch.cat([torch.from_numpy(splat.sh0), torch.from_numpy(splat.shN)], dim=1), degree)
    kp = data.camera.K  # OpenSplat's renderer centres the principal point: the project's is (W/2 - 0.5, H/2 - 0.5)
    if abs(kp[0, 2] - (data.camera.width / 2 - 0.5)) > 1e-6 or abs(kp[1, 2] - (data.camera.height / 2 - 0.5)) > 1e-6:
        raise SystemExit(f"the project's principal point {kp[0, 2]}, {kp[1, 2]} is not the image centre: "
                         "OpenSplat's renderer cannot render its camera")
    rows = []
    for _, view_id, name in held:
        view, im = tests[view_id], images[name]
        cam = cams[im["camera_id"]]
        gt_p = torch.from_numpy(view.image.astype(np.float32) / 255.0)
        gt_o, fx, fy = prepare_like_opensplat(sample / "images" / name, cam, downscale)
        h, w = gt_o.shape[:2]
        k0 = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], np.float32)
        k0[:2] *= np.float32(1.0 / downscale)
        new_k, _ = opencv46_new_camera_matrix(k0, np.array(cam["dist"] + [0.0] * 4, np.float32),
                                              cam["width"] // downscale, cam["height"] // downscale)
        scales, opac = model.render_scales_opacities()
        rgb, _, _, _ = rasterize(model.means, model.quats, scales, opac, model.sh_coeffs(model.sh_degree),
                                 torch.from_numpy(view.viewmat).float()[None], torch.from_numpy(new_k)[None], w, h,
                                 sh_degree=model.sh_degree, antialiased=model.antialiased)
        view_c = np.eye(4, dtype=np.float32)
        view_c[:3, :3] = _quat_to_rot(im["q"])
        view_c[:3, 3] = im["t"]
        os_own = _to_u8_like_opensplat(opensplat_cpu_render(*os_args, view_c, fx, fy, w, h))
        os_p = _to_u8_like_opensplat(opensplat_cpu_render(*os_args, view_c, float(kp[0, 0]), float(kp[1, 1]),
                                                          data.camera.width, data.camera.height))
        rows.append({"image": name,
                     "project_on_own_gt": psnr(render_view(model, view, data), gt_p, valid),
                     "project_on_opensplat_gt": psnr(rgb[0].clamp(0.0, 1.0),
                                                     torch.from_numpy(gt_o / np.float32(255.0))),
                     "opensplat_on_own_gt": _psnr_u8(os_own, gt_o),
                     "opensplat_on_project_gt": psnr(torch.from_numpy(os_p / np.float32(255.0)), gt_p, valid)})
    keys = [k for k in rows[0] if k != "image"]
    return {"n_views": len(rows), "mean": {k: float(np.mean([r[k] for r in rows])) for k in keys}, "per_view": rows,
            "principal_point_offset_px": [float(w / 2 - 0.5 - new_k[0, 2]), float(h / 2 - 0.5 - new_k[1, 2])]}


def ply_iteration(ply: Path) -> int | None:
    """The step OpenSplat wrote ``ply`` at (its header comment ``Generated by opensplat at iteration N``)."""
    with ply.open("rb") as fh:
        for _ in range(64):
            line = fh.readline().decode("ascii", "replace").strip()
            if line.startswith("comment Generated by opensplat at iteration "):
                return int(line.rsplit(" ", 1)[1])
            if line == "end_header":
                break
    return None


def add_val_check(result: dict[str, Any], ply: Path, val_name: str | None, steps: int) -> None:
    """``val_check`` and ``holdout_psnr_valid`` from OpenSplat's own render of the ``--val`` view, if any."""
    own = ply.parent / "val_render" / f"{steps}.png"
    ours = ply.parent / "holdout" / f"{Path(val_name).stem}.png" if val_name else None
    if ours is None or not own.is_file() or not ours.is_file():
        return
    result["val_check"] = {"image": val_name, "own_render": str(own), **check_against_own_render(ours, own)}
    # the multi-view figure stands only if our render of the PLY is OpenSplat's own render
    agree = result["val_check"]["ours_vs_own_render_psnr"] >= VAL_CHECK_MIN_PSNR
    result["agreement_with_own_render_psnr"] = result["val_check"]["ours_vs_own_render_psnr"]
    result["holdout_psnr_valid"] = agree
    if not agree:
        print(f"WARNING: this script's render of OpenSplat's PLY differs from OpenSplat's own render of "
              f"{val_name} ({result['val_check']['ours_vs_own_render_psnr']:.1f} dB < "
              f"{VAL_CHECK_MIN_PSNR} dB): the multi-view holdout_psnr is not OpenSplat's; "
              "use own_render_vs_gt_psnr (1 view)", file=sys.stderr)


# ----------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--opensplat", type=Path, default=None, help="the OpenSplat binary (not needed with --score-only)")
    p.add_argument("--sample", required=True,
                   help="skull, fox, or a folder with sparse/0 and images (then give --pair)")
    p.add_argument("--pair", nargs=2, default=None, metavar=("A", "B"),
                   help="two photos 1 m apart for the import's scale (default: the sample's)")
    p.add_argument("--steps", type=int, default=2000, help="steps of both trainings (default: %(default)s)")
    p.add_argument("--downscale", type=int, default=2,
                   help="image downscale of both (the fast preset's is 2; default: %(default)s)")
    p.add_argument("--opensplat-schedule", choices=["fast", "defaults"], default="fast",
                   help="OpenSplat's step options: the fast preset's schedule as fractions of --steps, or "
                        "OpenSplat's defaults (tuned for 30k steps) (default: %(default)s)")
    p.add_argument("--points", choices=["all", "train"], default="all",
                   help="OpenSplat's initial points: all of the model's (what the project starts from when its "
                        "own triangulation of the training views is too sparse and it falls back to the imported "
                        "points) or those two training photos observe (default: %(default)s)")
    p.add_argument("--no-val-check", dest="val_check", action="store_false",
                   help="do not leave one held-out photo in OpenSplat's input for its --val/--val-render (by "
                        "default the middle one is, and OpenSplat's own render of it is compared with ours)")
    p.add_argument("--work", type=Path, default=None, help="work folder (default: /tmp/opensplat-compare-<sample>)")
    p.add_argument("--skip-project", action="store_true", help="only OpenSplat (the split is still the project's)")
    p.add_argument("--skip-opensplat", action="store_true", help="only the project")
    p.add_argument("--score-only", type=Path, default=None, metavar="PLY",
                   help="train nothing: rescore this OpenSplat PLY (its step from its header, else --steps; the "
                        "split from --work's imported scene; OpenSplat's own render val_render/<step>.png next to "
                        "it, if there, is the check) and report the project's figures from --work/scene/splat")
    p.add_argument("--cross-gt", action="store_true",
                   help="with the project's and OpenSplat's models both there: also score each against the other "
                        "tool's preparation of the held-out photos (cross_ground_truth)")
    p.add_argument("--json", type=Path, default=None, help="also write the result here")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.sample in SAMPLES:
        sample, pair = SAMPLES[args.sample]
    else:
        sample, pair = Path(args.sample), None
    pair = tuple(args.pair) if args.pair else pair
    if pair is None:
        raise SystemExit("--pair A B is needed for a sample that is not skull or fox")
    work = args.work or Path(f"/tmp/opensplat-compare-{sample.name}")
    work.mkdir(parents=True, exist_ok=True)
    scene = work / "scene"
    from brave6d.training.presets import get_preset

    if get_preset("fast").downscale != args.downscale:
        print(f"note: the fast preset trains at 1/{get_preset('fast').downscale}, OpenSplat at 1/{args.downscale}",
              file=sys.stderr)
    if args.score_only is not None:
        args.skip_project = args.skip_opensplat = True
    elif not args.skip_opensplat and args.opensplat is None:
        raise SystemExit("--opensplat BINARY is needed (or --skip-opensplat / --score-only PLY)")
    if not args.skip_project or not (scene / "capture" / "frames.jsonl").is_file():
        import_scene(sample, pair, scene, work)  # (--skip-project keeps an imported, trained scene)
    held = predicted_holdout(scene)
    held_names = [name for _, _, name in held]
    result: dict[str, Any] = {"sample": str(sample), "steps": args.steps, "downscale": args.downscale,
                              "holdout_images": held_names, "holdout_rule": "the project's: 10% evenly spaced"}
    val_name = held_names[len(held_names) // 2] if args.val_check else None
    options = opensplat_options(args.steps, args.opensplat_schedule)
    if not args.skip_project:
        proj = train_project(scene, args.steps, work)
        if proj["holdout_view_ids"] != [vid for _, vid, _ in held]:
            raise SystemExit(f"the project held out {proj['holdout_view_ids']}, predicted {held}")
        result["project"] = proj
    elif (scene / "splat" / "metrics.json").is_file():  # an earlier run's training of this scene, for reference
        m = json.loads((scene / "splat" / "metrics.json").read_text())
        result["project_earlier"] = {"holdout_psnr": m["holdout"]["psnr"], "n_holdout_views": m["holdout"]["n_views"],
                                     "steps": m["steps"], "train_time_s": m["train_time_s"]}
        if "per_view" in m["holdout"]:
            result["project_earlier"]["per_view"] = m["holdout"]["per_view"]
    if not args.skip_opensplat:
        ws = work / "opensplat_ws"
        result["opensplat_workspace"] = write_workspace(sample, ws, set(held_names), args.points, val_name)
        ply = work / "opensplat" / "splat.ply"
        ply.parent.mkdir(parents=True, exist_ok=True)
        run = train_opensplat(args.opensplat.resolve(), ws, ply, args.steps, args.downscale, options, work, val_name)
        interval = options.get("sh-degree-interval", OPENSPLAT_STEP_OPTIONS["sh-degree-interval"])
        t0 = time.perf_counter()
        ev = evaluate_opensplat(ply, sample, held_names, args.steps, args.downscale, interval,
                                work / "opensplat" / "holdout")
        result["opensplat"] = {**run, "options": options, **ev, "eval_s": time.perf_counter() - t0}
        add_val_check(result["opensplat"], ply, val_name, args.steps)
    if args.score_only is not None:
        ply = args.score_only.resolve()
        steps = ply_iteration(ply) or args.steps
        options = opensplat_options(steps, args.opensplat_schedule)
        interval = options.get("sh-degree-interval", OPENSPLAT_STEP_OPTIONS["sh-degree-interval"])
        t0 = time.perf_counter()
        ev = evaluate_opensplat(ply, sample, held_names, steps, args.downscale, interval, ply.parent / "holdout")
        result["steps"] = steps
        result["opensplat"] = {"ply": str(ply), "steps": steps, "options_assumed": options, **ev,
                               "eval_s": time.perf_counter() - t0}
        add_val_check(result["opensplat"], ply, val_name, steps)
    if args.cross_gt and "opensplat" in result and (scene / "splat" / "point_cloud.ply").is_file():
        ply = Path(result["opensplat"].get("ply", work / "opensplat" / "splat.ply"))
        steps = result["steps"]
        interval = opensplat_options(steps, args.opensplat_schedule).get(
            "sh-degree-interval", OPENSPLAT_STEP_OPTIONS["sh-degree-interval"])
        result["cross_ground_truth"] = cross_ground_truth(ply, scene, sample, held, steps, args.downscale, interval)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json is not None:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
