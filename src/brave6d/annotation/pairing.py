"""Pair the camera poses of a 3D-DAT scene with captured views, then align the two frames.

3D-DAT pairs line ``i`` of ``groundtruth_handeye.txt`` with image ``i`` of its sorted rgb files
and never reads the ids (see :mod:`brave6d.annotation.threedat`). The candidate pairings, in order:

1. ``rgb files`` (3D-DAT's own): line ``i`` with the captured view that image ``i`` names (its
   file stem is the captured image's stem, the view id or the frame index);
2. ``frame index``: every line id is a captured frame index;
3. ``view id``: every line id is a captured view id;
4. ``order``: line ``i`` with the ``i``-th captured view, when the counts agree.

Pairings that give the same views are merged (the ids then cross-check the images). The first
pairing whose camera poses align (:func:`brave6d.annotation.alignment.estimate_alignment`) is used; a
warning says when an earlier one did not align or when the ids disagree with the images. When
none aligns, the error names each pairing tried, since a wrong pairing shows only as a residual.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brave6d.annotation.alignment import (AlignmentError, AlignmentOptions, AlignmentReport, alignment_problem,
                                  estimate_alignment)
from brave6d.annotation.threedat import CameraPose, ThreeDatScene
from brave6d.core.errors import DataError
from brave6d.core.layout import FrameRecord

Matrix4 = NDArray[np.float64]
Captured = Sequence[tuple[FrameRecord, Matrix4]]
View = tuple[CameraPose, FrameRecord, Matrix4]

#: Pairings by what the 3D-DAT folder says about the views (not by mere order).
KEYED = ("rgb files", "frame index", "view id")


@dataclass(frozen=True)
class Pairing:
    """3D-DAT camera poses paired with captured views by one rule: ``how`` (its key), ``rule`` (what
    it pairs, for messages) and ``label`` (what it pairs by, for messages)."""

    how: str
    rule: str
    label: str
    views: tuple[View, ...]
    agrees: tuple[str, ...] = ()  # other rules that give the same views

    @property
    def indices(self) -> tuple[int, ...]:
        """The captured frame index of each line, in line order."""
        return tuple(r.index for _, r, _ in self.views)

    def merged(self, other: Pairing) -> Pairing:
        return Pairing(self.how, self.rule, self.label, self.views, (*self.agrees, other.how))


@dataclass(frozen=True)
class PairedAlignment:
    """The pairing used, its alignment report and warnings about the other pairings."""

    pairing: Pairing
    report: AlignmentReport
    warnings: tuple[str, ...]


def _record_of_image(image: Path, records: Sequence[FrameRecord]) -> FrameRecord | None:
    """The captured view an image names: same file stem as the captured image, else the view id,
    else (digits) the frame index."""
    stem = image.stem
    for key in (lambda r: Path(r.rgb).stem, lambda r: r.view_id):
        hits = [r for r in records if key(r) == stem]
        if hits:
            return hits[0]
    if stem.isdigit():
        return next((r for r in records if r.index == int(stem)), None)
    return None


def by_images(dat: ThreeDatScene, captured: Captured) -> Pairing | str:
    """3D-DAT's pairing (line ``i`` with image ``i``), or why the folder does not allow it."""
    rgb_dir = dat.config.show(dat.config.rgb_path(dat.scene_id))
    images, poses = dat.rgb_files, dat.camera_poses
    if not images:
        return f"{rgb_dir} holds no .png/.jpg images"
    if len(images) < len(poses):
        return f"{rgb_dir} holds {len(images)} images for {len(poses)} camera poses (3D-DAT needs one per pose)"
    by_record = {id(r): (r, T) for r, T in captured}
    records = [r for r, _ in captured]
    views: list[View] = []
    for pose, image in zip(poses, images):
        record = _record_of_image(image, records)
        if record is None:
            return f"{dat.config.show(image)} (paired with line {pose.line}) names no captured frame"
        views.append((pose, *by_record[id(record)]))
    used = [r.index for _, r, _ in views]
    if len(set(used)) != len(used):
        return f"the images in {rgb_dir} name some captured frame twice"
    return Pairing("rgb files", f"line order with the sorted images in {rgb_dir}", "the rgb images (as 3D-DAT)",
                   tuple(views))


def by_ids(dat: ThreeDatScene, captured: Captured) -> list[Pairing]:
    """Pairings by the line ids (frame index, view id) and by order, where the folder allows them."""
    poses = dat.camera_poses
    by_index = {r.index: (r, T) for r, T in captured}
    by_view = {r.view_id: (r, T) for r, T in captured}
    out = []
    if all(p.frame_id.isdigit() and int(p.frame_id) in by_index for p in poses) and \
            len({int(p.frame_id) for p in poses}) == len(poses):
        out.append(Pairing("frame index", "line id = captured frame index", "the ids as captured frame indices",
                           tuple((p, *by_index[int(p.frame_id)]) for p in poses)))
    if all(p.frame_id in by_view for p in poses):
        out.append(Pairing("view id", "line id = captured view id", "the ids as captured view ids",
                           tuple((p, *by_view[p.frame_id]) for p in poses)))
    if len(poses) == len(captured):
        ordered = sorted(captured, key=lambda rt: rt[0].index)
        out.append(Pairing("order", "line order with the captured frames in index order", "line order",
                           tuple((p, r, T) for p, (r, T) in zip(poses, ordered))))
    return out


def candidate_pairings(dat: ThreeDatScene, captured: Captured) -> tuple[list[Pairing], list[str]]:
    """The pairings to try, 3D-DAT's first, equal ones merged; and why 3D-DAT's is unavailable."""
    first = by_images(dat, captured)
    found = ([first] if isinstance(first, Pairing) else []) + by_ids(dat, captured)
    notes = [] if isinstance(first, Pairing) else [first]
    merged: list[Pairing] = []
    for pairing in found:
        same = next((i for i, m in enumerate(merged) if m.indices == pairing.indices), None)
        if same is None:
            merged.append(pairing)
        else:
            merged[same] = merged[same].merged(pairing)
    return merged, notes


def _short(report: AlignmentReport) -> str:
    if not report.applied:
        return f"{report.frames} views differ by up to {report.max_mm:.2f} mm, too few to align"
    return f"residual RMS {report.rms_mm:.2f} mm / {report.rms_deg:.3f} deg"


def _disagreements(chosen: Pairing, others: Sequence[Pairing], traj: str) -> list[str]:
    """Warnings about keyed pairings (not tried) that give other views than the one used."""
    out = []
    for other in others:
        if other.how not in KEYED:
            continue
        line, a, b = next((p.line, r.index, o.index) for (p, r, _), (_, o, _) in zip(chosen.views, other.views)
                          if r.index != o.index)
        out.append(f"{traj}: {other.label} pair line {line} with captured frame {b}, {chosen.label} with frame "
                   f"{a}; paired by {chosen.label}")
    return out


def _warnings(dat: ThreeDatScene, chosen: Pairing, tried: Sequence[tuple[Pairing, AlignmentReport, str]],
              untried: Sequence[Pairing], notes: Sequence[str]) -> list[str]:
    """What the user should know about the pairing used: pairings that did not align, keyed ones
    that disagree, images that could not be used, images left without a pose."""
    traj = dat.config.show(dat.files["camera_poses"])
    out = [f"{traj}: camera poses paired by {p.rule} do not align ({_short(r)}); paired by {chosen.rule}"
           for p, r, _ in tried]
    out += _disagreements(chosen, untried, traj)
    if dat.rgb_files and notes:
        out.extend(f"{note}; paired by {chosen.label}" for note in notes)
    if chosen.how == "order" and not any(p.how in KEYED for p, _, _ in tried):
        out.append(f"{traj}: neither images nor ids name the captured views; paired by {chosen.rule}")
    if chosen.how == "rgb files" and len(dat.rgb_files) > len(dat.camera_poses):
        extra = len(dat.rgb_files) - len(dat.camera_poses)
        out.append(f"{dat.config.show(dat.config.rgb_path(dat.scene_id))} holds {len(dat.rgb_files)} images for "
                   f"{len(dat.camera_poses)} camera poses: the last {extra} (sorted) have no pose, as in 3D-DAT")
    return out


def pair_and_align(dat: ThreeDatScene, captured: Captured,
                   options: AlignmentOptions = AlignmentOptions()) -> PairedAlignment:
    """Pair the 3D-DAT camera poses with captured views and align the frames (module docstring).

    Raises DataError when no pairing is possible and AlignmentError when none aligns; both name
    the pairings considered.
    """
    traj = dat.config.show(dat.files["camera_poses"])
    candidates, notes = candidate_pairings(dat, captured)
    if not candidates:
        raise DataError(f"{traj}: the {len(dat.camera_poses)} camera poses (ids like {dat.camera_poses[0].frame_id!r}) "
                        f"cannot be paired with the {len(captured)} captured views: {'; '.join(notes)}; the ids are "
                        "neither captured frame indices nor view ids and the counts differ")
    tried: list[tuple[Pairing, AlignmentReport, str]] = []
    for n, pairing in enumerate(candidates):
        report = estimate_alignment([T for _, _, T in pairing.views], [p.world_T_cam for p, _, _ in pairing.views],
                                    [p.frame_id for p, _, _ in pairing.views], options)
        problem = alignment_problem(report)
        if problem is None:
            return PairedAlignment(pairing, report, tuple(_warnings(dat, pairing, tried, candidates[n + 1:], notes)))
        tried.append((pairing, report, problem))
    first, _, problem = tried[0]
    others = "".join(f"; paired by {p.rule}: {_short(r)}" for p, r, _ in tried[1:])
    why = f" (no pairing by images: {'; '.join(notes)})" if notes else ""
    raise AlignmentError(
        f"{traj}: camera poses paired by {first.rule}: {problem}{others}{why}. A wrong pairing shows as such a "
        "residual: 3D-DAT pairs the lines with its sorted rgb images and ignores the ids, so name the images as "
        "the captured ones (e.g. 000005.png) or make the ids the captured frame indices")
