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
4. scores OpenSplat's PLY on the held-out photos exactly as OpenSplat prepares its own images
   (OpenCV: resize by 1/D with INTER_AREA, ``getOptimalNewCameraMatrix`` with alpha 0,
   ``undistort``, ROI crop), rendered with the project's rasterizer in OpenSplat's conventions
   (its fixed background colour, the SH degree it had reached, the COLMAP pose, the new K as
   OpenCV's pixel convention as OpenSplat's CPU rasterizer uses it).

Both figures are the mean PSNR over the same held-out photos, each tool at its own preparation of
those photos at the same downscale (the project's images are undistorted once at full size, then
resampled, so the two ground truths differ by resampling only). It prints one JSON object: holdout
PSNR of each, the number of views each rests on, wall times.

    python benchmarks/opensplat_compare.py --opensplat /path/to/opensplat --sample skull [--steps 2000]
        [--work /tmp/osc-skull] [--json out.json] [--opensplat-schedule fast|defaults] [--skip-project]
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
    return {"ours_vs_own_render_psnr": _psnr(ours, own), "own_render_vs_gt_psnr": _psnr(own, gt),
            "ours_vs_gt_psnr": _psnr(ours, gt)}


def evaluate_opensplat(ply: Path, sample: Path, held_names: list[str], steps: int, downscale: int,
                       sh_interval: int, write_dir: Path | None = None) -> dict[str, Any]:
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
    scales = torch.exp(torch.from_numpy(splat.scales))
    opac = torch.sigmoid(torch.from_numpy(splat.opacities))
    colors = torch.cat([torch.from_numpy(splat.sh0), torch.from_numpy(splat.shN)], dim=1)[:, :n_sh]
    bg = torch.tensor(OPENSPLAT_BACKGROUND, dtype=torch.float32)
    per_view = []
    for name in held_names:
        im = images[name]
        cam = cams[im["camera_id"]]
        bgr = cv2.imread(str(sample / "images" / name), cv2.IMREAD_COLOR)
        img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        fx, fy, cx, cy = cam["fx"], cam["fy"], cam["cx"], cam["cy"]
        if img.shape[0] != cam["height"] or img.shape[1] != cam["width"]:
            r = img.shape[0] / cam["height"]
            fx, fy, cx, cy = fx * r, fy * r, cx * r, cy * r
        if downscale > 1:
            img = cv2.resize(img, None, fx=1.0 / downscale, fy=1.0 / downscale, interpolation=cv2.INTER_AREA)
            fx, fy, cx, cy = fx / downscale, fy / downscale, cx / downscale, cy / downscale
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float32)
        dist = np.array(cam["dist"] + [0.0, 0.0, 0.0, 0.0], np.float32)  # k1 k2 p1 p2 k3 k4 k5 k6 as OpenSplat
        if np.any(dist != 0):
            newK, roi = cv2.getOptimalNewCameraMatrix(K, dist, (img.shape[1], img.shape[0]), 0)
            img = cv2.undistort(img, K, dist, None, newK)
            x, y, w, h = roi
            img = img[y:y + h, x:x + w]
            K = newK.astype(np.float32)
        gt = torch.from_numpy(img.astype(np.float32) / 255.0)
        h, w = gt.shape[:2]
        view = np.eye(4, dtype=np.float32)
        view[:3, :3] = _quat_to_rot(im["q"])
        view[:3, 3] = im["t"]
        rgb, _, _, _ = rasterize(means, quats, scales, opac, colors, torch.from_numpy(view)[None],
                                 torch.from_numpy(K)[None], w, h, sh_degree=degree, backgrounds=bg[None],
                                 backend="cpu")
        render = rgb[0].clamp(0.0, 1.0)
        mse = float(torch.mean((render - gt) ** 2))
        per_view.append({"image": name, "psnr": -10.0 * math.log10(max(mse, 1e-12)), "size": f"{w}x{h}"})
        if write_dir is not None:
            write_dir.mkdir(parents=True, exist_ok=True)
            side = torch.cat([render, gt], dim=1).numpy()
            cv2.imwrite(str(write_dir / f"{Path(name).stem}.png"),
                        cv2.cvtColor((side * 255 + 0.5).clip(0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    return {"holdout_psnr": float(np.mean([v["psnr"] for v in per_view])), "n_holdout_views": len(per_view),
            "sh_degree_rendered": degree, "num_gaussians": splat.num_gaussians, "per_view": per_view}


# ----------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--opensplat", type=Path, required=True, help="the OpenSplat binary")
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
    if not args.skip_project or not (scene / "capture" / "frames.jsonl").is_file():
        import_scene(sample, pair, scene, work)  # (--skip-project keeps an imported, trained scene)
    held = predicted_holdout(scene)
    held_names = [name for _, _, name in held]
    result: dict[str, Any] = {"sample": str(sample), "steps": args.steps, "downscale": args.downscale,
                              "holdout_images": held_names, "holdout_rule": "the project's: 10% evenly spaced"}
    if not args.skip_project:
        proj = train_project(scene, args.steps, work)
        if proj["holdout_view_ids"] != [vid for _, vid, _ in held]:
            raise SystemExit(f"the project held out {proj['holdout_view_ids']}, predicted {held}")
        result["project"] = proj
    elif (scene / "splat" / "metrics.json").is_file():  # an earlier run's training of this scene, for reference
        m = json.loads((scene / "splat" / "metrics.json").read_text())
        result["project_earlier"] = {"holdout_psnr": m["holdout"]["psnr"], "n_holdout_views": m["holdout"]["n_views"],
                                     "steps": m["steps"], "train_time_s": m["train_time_s"]}
    if not args.skip_opensplat:
        ws = work / "opensplat_ws"
        val_name = held_names[len(held_names) // 2] if args.val_check else None
        result["opensplat_workspace"] = write_workspace(sample, ws, set(held_names), args.points, val_name)
        options = opensplat_options(args.steps, args.opensplat_schedule)
        ply = work / "opensplat" / "splat.ply"
        ply.parent.mkdir(parents=True, exist_ok=True)
        run = train_opensplat(args.opensplat.resolve(), ws, ply, args.steps, args.downscale, options, work, val_name)
        interval = options.get("sh-degree-interval", OPENSPLAT_STEP_OPTIONS["sh-degree-interval"])
        t0 = time.perf_counter()
        ev = evaluate_opensplat(ply, sample, held_names, args.steps, args.downscale, interval,
                                work / "opensplat" / "holdout")
        result["opensplat"] = {**run, "options": options, **ev, "eval_s": time.perf_counter() - t0}
        own = ply.parent / "val_render" / f"{args.steps}.png"
        if val_name is not None and own.is_file():
            result["opensplat"]["val_check"] = {"image": val_name, **check_against_own_render(
                ply.parent / "holdout" / f"{Path(val_name).stem}.png", own)}
            # the multi-view figure stands only if our render of the PLY is OpenSplat's own render
            agree = result["opensplat"]["val_check"]["ours_vs_own_render_psnr"] >= VAL_CHECK_MIN_PSNR
            result["opensplat"]["holdout_psnr_valid"] = agree
            if not agree:
                print(f"WARNING: this script's render of OpenSplat's PLY differs from OpenSplat's own render of "
                      f"{val_name} ({result['opensplat']['val_check']['ours_vs_own_render_psnr']:.1f} dB < "
                      f"{VAL_CHECK_MIN_PSNR} dB): the multi-view holdout_psnr is not OpenSplat's; "
                      "use own_render_vs_gt_psnr (1 view)", file=sys.stderr)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json is not None:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
