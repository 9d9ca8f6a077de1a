"""How tests/data/real/fox was made from instant-ngp's ``data/nerf/fox`` (see README.md).

    python tests/data/real/fox/make_sample.py INSTANT_NGP_CHECKOUT/data/nerf/fox

- ``transforms.json``: copied byte for byte (the point of the sample: the file as instant-ngp ships it);
- ``images/NNNN.jpg``: each 1080x1920 photo resampled to 1/4 (270x480, area averaging) and saved as
  JPEG quality 85 without metadata; the names stay, so the file's ``file_path`` entries still hold;
- ``sparse/0/``: COLMAP's own model of the shipped photos (pycolmap: SIFT, exhaustive matching,
  incremental mapping with one shared OPENCV camera started from the file's focal length), written
  by COLMAP as binary. Nothing of instant-ngp's poses goes into it: the tests compare the two.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import pycolmap

FACTOR = 4
QUALITY = 85


def main(source: Path, out: Path) -> None:
    (out / "images").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source / "transforms.json", out / "transforms.json")
    for photo in sorted((source / "images").glob("*.jpg")):
        image = cv2.imread(str(photo), cv2.IMREAD_COLOR)
        h, w = image.shape[:2]
        small = cv2.resize(image, (w // FACTOR, h // FACTOR), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / "images" / photo.name), small, [cv2.IMWRITE_JPEG_QUALITY, QUALITY])


def reconstruct(out: Path, focal: float, work: Path) -> pycolmap.Reconstruction:
    """COLMAP's reconstruction of ``out/images`` (one camera), written to ``out/sparse/0``."""
    first = cv2.imread(str(next((out / "images").glob("*.jpg"))))
    h, w = first.shape[:2]
    reader = pycolmap.ImageReaderOptions(camera_model="OPENCV",
                                         camera_params=f"{focal},{focal},{w / 2},{h / 2},0,0,0,0")
    db = work / "database.db"
    pycolmap.extract_features(db, out / "images", camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    models = pycolmap.incremental_mapping(db, out / "images", work / "sparse")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    target = out / "sparse" / "0"
    target.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(target))
    return rec


if __name__ == "__main__":
    import json
    import tempfile

    here = Path(__file__).resolve().parent
    main(Path(sys.argv[1]), here)
    focal = json.loads((here / "transforms.json").read_text())["fl_x"] / FACTOR
    with tempfile.TemporaryDirectory() as work:
        rec = reconstruct(here, focal, Path(work))
    print(rec.summary())
