"""World-frame triangle meshes with appearance, prepared once for CPU ray casting.

A :class:`SceneModel` holds every surface of a scene spec in the world (robot base) frame:
the annotated objects, the static meshes (table, clutter) and, on request, the ChArUco
board. Geometry lives in an Open3D ``RaycastingScene`` (one geometry per loaded mesh
piece); appearance lives in flat per-triangle NumPy arrays indexed by a *global triangle
index* (``geometry_offset[geometry_id] + primitive_id``) so that shading is vectorised.

Segment ids (what :class:`~brave6d.capture.sim_camera.SimCamera` writes per pixel):

* ``0``                       nothing hit (background),
* ``1 .. K``                  the spec's ``objects`` in spec order (the object-id buffer value),
* ``STATIC_ID_BASE + i``      ``static_meshes[i]``,
* ``BOARD_SEGMENT_ID``        the ChArUco board.

The object-id buffer keeps only ``1 .. K`` (everything else is 0).

Appearance: a triangle is either *textured* (``tri_texture >= 0``: per-corner UVs into a
texture with a mip pyramid; all pyramids are packed into one :class:`TextureAtlas`) or *vertex
coloured* (``tri_texture == -1``: per-corner colours;
uniform and face colours are stored the same way). Colours are kept as *linear* RGB in
[0, 1] (8-bit sRGB files are decoded once here); plain meshes get :data:`DEFAULT_GREY`.
UVs follow the OBJ convention: ``(0, 0)`` is the bottom-left of the texture image.

The board is a flat textured quad (two triangles, with a white paper margin) cast in its
own small ray-casting scene and merged with a small depth tolerance, so a board lying on
the table wins the tie instead of z-fighting with the table top.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import open3d as o3d
import trimesh
from numpy.typing import NDArray

from brave6d.core.board import board_image, board_size_m
from brave6d.core.errors import DataError
from brave6d.core.spec import BoardSpec, MeshSpec, SceneSpec
from brave6d.core.transforms import check_rigid, transform_points

#: Segment id of ``static_meshes[i]`` is ``STATIC_ID_BASE + i``.
STATIC_ID_BASE = 1000
#: Segment id of the ChArUco board.
BOARD_SEGMENT_ID = 60000
#: Most objects a scene may have (their ids must stay below the static range).
MAX_OBJECTS = STATIC_ID_BASE - 1
#: sRGB colour of meshes without colours or texture.
DEFAULT_GREY = (160, 160, 160)
#: Board pixels per metre of the texture (0.25 mm texels: sharp at 20 cm).
DEFAULT_BOARD_PX_PER_M = 4000.0
#: White paper margin around the printed pattern, in squares.
BOARD_MARGIN_SQUARES = 0.5
#: A board hit wins over a mesh hit that is at most this much closer (z-depth, metres).
BOARD_TIE_TOLERANCE_M = 1e-3

SegmentKind = Literal["object", "static", "board"]


# ----------------------------------------------------------------------------- colour helpers
def srgb_to_linear(values: NDArray[np.floating] | NDArray[np.integer]) -> NDArray[np.float32]:
    """8-bit sRGB (0..255) -> linear RGB in [0, 1] (IEC 61966-2-1 curve)."""
    x = np.asarray(values, dtype=np.float32) / np.float32(255.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb_dn(linear: NDArray[np.floating]) -> NDArray[np.float32]:
    """Linear RGB -> sRGB digital numbers as float32 in [0, 255] (clipped, not rounded)."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, x * np.float32(12.92), np.float32(1.055) * np.power(x, np.float32(1 / 2.4)) - np.float32(0.055))
    return (srgb * np.float32(255.0)).astype(np.float32)


# ----------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class MeshPart:
    """One triangle mesh already in the world frame, with its appearance and segment id.

    Exactly one appearance source is used, in this order: ``texture`` + ``uv`` (per vertex),
    ``vertex_colors``, ``face_colors``, ``color``. Colours and textures are 8-bit sRGB.
    """

    name: str
    segment_id: int
    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    uv: NDArray[np.float64] | None = None
    texture: NDArray[np.uint8] | None = None
    vertex_colors: NDArray[np.uint8] | None = None
    face_colors: NDArray[np.uint8] | None = None
    color: tuple[int, int, int] = DEFAULT_GREY
    source: str = "<memory>"

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces, dtype=np.int64)
        where = f"{self.source} ({self.name})"
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise DataError(f"{where}: expected (V, 3) vertices and (F, 3) faces, got {v.shape} and {f.shape}")
        if len(f) == 0:
            raise DataError(f"{where}: mesh has no triangles")
        if not np.all(np.isfinite(v)):
            raise DataError(f"{where}: vertices contain NaN or inf")
        if f.min() < 0 or f.max() >= len(v):
            raise DataError(f"{where}: face indices out of range (0..{len(v) - 1})")
        if self.texture is not None:
            if self.uv is None or np.asarray(self.uv).shape != (len(v), 2):
                raise DataError(f"{where}: textured mesh needs (V, 2) UV coordinates")
            if not np.all(np.isfinite(self.uv)):
                raise DataError(f"{where}: UV coordinates contain NaN or inf")
            tex = np.asarray(self.texture)
            if tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8:
                raise DataError(f"{where}: texture must be (H, W, 3) uint8 RGB, got {tex.dtype} {tex.shape}")
            if max(tex.shape[:2]) >= 32767:
                raise DataError(f"{where}: texture {tex.shape[1]}x{tex.shape[0]} is too large (max 32766 px a side)")
        if self.vertex_colors is not None and np.asarray(self.vertex_colors).shape != (len(v), 3):
            raise DataError(f"{where}: vertex colours must be (V, 3) uint8")
        if self.face_colors is not None and np.asarray(self.face_colors).shape != (len(f), 3):
            raise DataError(f"{where}: face colours must be (F, 3) uint8")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)


@dataclass(frozen=True)
class Segment:
    """What a segment id stands for."""

    segment_id: int
    name: str
    kind: SegmentKind
    source: str


@dataclass(frozen=True)
class Texture:
    """A texture as a mip pyramid of linear RGB float32 images (level 0 = full size)."""

    levels: tuple[NDArray[np.float32], ...]
    source: str

    @classmethod
    def from_srgb(cls, image: NDArray[np.uint8], source: str) -> Texture:
        """Decode 8-bit sRGB to linear and build the pyramid by 2x2 area averaging."""
        level = np.ascontiguousarray(srgb_to_linear(image))
        levels = [level]
        while max(level.shape[:2]) > 1:
            h, w = level.shape[:2]
            level = cv2.resize(level, (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA)
            if level.ndim == 2:  # cv2 drops a singleton channel axis; never happens for 3 channels
                level = level[:, :, None]
            levels.append(np.ascontiguousarray(level, dtype=np.float32))
        return cls(tuple(levels), source)


#: Wrap-around border (texels) right of and below each level in the atlas, so that bilinear
#: lookups at the last column/row read the first ones (OBJ "repeat" addressing).
_ATLAS_GUTTER = 2
_ATLAS_MAX_SIDE = 32766  # cv2.remap limit


@dataclass(frozen=True)
class TextureAtlas:
    """Every mip level of every texture packed into one float32 image (shelf packing), so that
    shading samples all textured pixels with two ``cv2.remap`` calls.

    Level ``k`` of texture ``i`` is entry ``first_level[i] + k`` of ``offset`` (x, y of its
    top-left texel in the atlas) and ``size`` (w, h); ``level_count[i]`` levels per texture.
    """

    image: NDArray[np.float32]
    offset: NDArray[np.float32]
    size: NDArray[np.float32]
    first_level: NDArray[np.int64]
    level_count: NDArray[np.int64]

    @classmethod
    def build(cls, textures: Sequence[Texture]) -> TextureAtlas:
        """Pack the pyramids (tallest levels first, rows of at most ``width`` texels)."""
        levels = [(i, k, lvl) for i, tex in enumerate(textures) for k, lvl in enumerate(tex.levels)]
        if not levels:
            return cls(np.zeros((1, 1, 3), np.float32), np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32),
                       np.zeros(0, np.int64), np.zeros(0, np.int64))
        g = _ATLAS_GUTTER
        area = sum((lvl.shape[0] + g) * (lvl.shape[1] + g) for _, _, lvl in levels)
        widest = max(lvl.shape[1] + g for _, _, lvl in levels)
        width = int(min(_ATLAS_MAX_SIDE, max(widest, math.ceil(math.sqrt(area) * 1.2))))
        order = sorted(range(len(levels)), key=lambda j: -levels[j][2].shape[0])
        first_level = np.cumsum([0] + [len(t.levels) for t in textures])[:-1]
        offset = np.zeros((len(levels), 2), np.float32)
        size = np.zeros((len(levels), 2), np.float32)
        x = y = shelf = 0
        placed = []
        for j in order:
            i, k, lvl = levels[j]
            h, w = lvl.shape[0] + g, lvl.shape[1] + g
            if x + w > width:
                x, y, shelf = 0, y + shelf, 0
            placed.append((i, k, lvl, x, y))
            x, shelf = x + w, max(shelf, h)
        height = y + shelf
        if height > _ATLAS_MAX_SIDE:
            sources = ", ".join(sorted({t.source for t in textures}))
            raise DataError(f"textures too large to pack ({area / 1e6:.0f} Mtexels in {sources}): downsample them")
        image = np.zeros((height, width, 3), np.float32)
        for i, k, lvl, x0, y0 in placed:
            h, w = lvl.shape[:2]
            image[y0:y0 + h + g, x0:x0 + w + g] = np.pad(lvl, ((0, g), (0, g), (0, 0)), mode="wrap")
            offset[first_level[i] + k] = (x0, y0)
            size[first_level[i] + k] = (w, h)
        return cls(image, offset, size, first_level.astype(np.int64),
                   np.array([len(t.levels) for t in textures], np.int64))


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays.

    ``hit`` (N,) bool; ``triangle`` (N,) int64 global triangle index (-1 = none); ``bary``
    (N, 2) float32 Embree barycentrics ``(u, v)`` with the hit point
    ``(1-u-v) p0 + u p1 + v p2``; ``t`` (N,) float32 ray parameter (inf = none).
    """

    hit: NDArray[np.bool_]
    triangle: NDArray[np.int64]
    bary: NDArray[np.float32]
    t: NDArray[np.float32]


# ----------------------------------------------------------------------------- mesh loading
def _trimesh_appearance(mesh: trimesh.Trimesh, where: str) -> dict[str, object]:
    """Appearance of a loaded trimesh as :class:`MeshPart` keyword arguments."""
    visual = mesh.visual
    kind = getattr(visual, "kind", None)
    if kind == "texture":
        material = visual.material
        image = getattr(material, "image", None)
        if image is None:
            image = getattr(material, "baseColorTexture", None)
        uv = getattr(visual, "uv", None)
        if image is not None and uv is not None and len(uv) == len(mesh.vertices):
            return {"texture": np.ascontiguousarray(np.asarray(image.convert("RGB"), dtype=np.uint8)),
                    "uv": np.asarray(uv, dtype=np.float64)}
        if image is not None:
            raise DataError(f"{where}: textured mesh has no per-vertex UV coordinates")
        main = getattr(material, "main_color", None)
        if main is not None:
            return {"color": tuple(int(c) for c in np.asarray(main)[:3])}
        return {}
    if kind == "vertex":
        return {"vertex_colors": np.asarray(visual.vertex_colors, dtype=np.uint8)[:, :3].copy()}
    if kind == "face":
        return {"face_colors": np.asarray(visual.face_colors, dtype=np.uint8)[:, :3].copy()}
    return {}


def load_mesh_parts(path: Path, scale: float, world_T_mesh: NDArray[np.float64], segment_id: int,
                    name: str) -> list[MeshPart]:
    """Load a mesh file (OBJ+MTL+texture, PLY with colours, STL, GLB, ...) into world-frame parts.

    ``scale`` converts file units to metres and is applied before ``world_T_mesh``. A file
    with several pieces (OBJ groups with different materials) gives one part per piece.
    Errors name the file.
    """
    where = str(path)
    if not Path(path).is_file():
        raise DataError(f"{where}: mesh file not found")
    T = check_rigid(world_T_mesh, f"{where}: pose")
    try:
        loaded = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh raises many types for broken files
        raise DataError(f"{where}: cannot load mesh ({type(exc).__name__}: {exc})") from None
    pieces = [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if not pieces:
        raise DataError(f"{where}: file holds no triangles")
    parts = []
    for i, piece in enumerate(pieces):
        vertices = transform_points(T, np.asarray(piece.vertices, dtype=np.float64) * scale)
        parts.append(MeshPart(name=name if len(pieces) == 1 else f"{name}[{i}]", segment_id=segment_id,
                              vertices=vertices, faces=np.asarray(piece.faces, dtype=np.int64),
                              source=where, **_trimesh_appearance(piece, where)))  # type: ignore[arg-type]
    return parts


def board_part(board: BoardSpec, px_per_m: float = DEFAULT_BOARD_PX_PER_M,
               margin_squares: float = BOARD_MARGIN_SQUARES) -> MeshPart:
    """The ChArUco board as a textured quad at ``board.pose`` (two triangles, white margin).

    The texture comes from :func:`brave6d.core.board.board_image`, so it shows exactly the
    pattern that calibration detects, in the board frame of :mod:`brave6d.core.board`. The
    resolution is rounded to a whole number of pixels per square.
    """
    px_per_square = max(8, int(round(board.square_length_m * px_per_m)))
    ppm = px_per_square / board.square_length_m
    pattern = board_image(board, ppm)
    margin_px = int(round(margin_squares * px_per_square))
    texture = cv2.copyMakeBorder(pattern, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)
    texture = np.ascontiguousarray(np.repeat(texture[:, :, None], 3, axis=2))
    h_px, w_px = texture.shape[:2]
    width_m, height_m = board_size_m(board)
    m = margin_px / ppm
    corners = np.array([[-m, -m, 0.0], [width_m + m, -m, 0.0], [width_m + m, height_m + m, 0.0],
                        [-m, height_m + m, 0.0]])
    # Texture column of board x: x * ppm - 0.5 + margin (pixel-centre convention of board_image);
    # the sampler maps u to column u * W - 0.5 and v to row (1 - v) * H - 0.5.
    uv = np.stack([(corners[:, 0] * ppm + margin_px) / w_px, 1.0 - (corners[:, 1] * ppm + margin_px) / h_px], axis=1)
    vertices = transform_points(board.pose.matrix(), corners)
    return MeshPart(name="charuco_board", segment_id=BOARD_SEGMENT_ID, vertices=vertices,
                    faces=np.array([[0, 1, 2], [0, 2, 3]]), uv=uv, texture=texture, source="<board>")


# ----------------------------------------------------------------------------- the model
class SceneModel:
    """Every surface of a scene, ready for ray casting and vectorised shading.

    Build it with :meth:`from_spec` (or from :class:`MeshPart` lists for tests). Per-triangle
    arrays (global triangle index): ``tri_segment`` int32, ``tri_texture`` int32 (-1 =
    vertex colours), ``tri_uv`` (T, 3, 2) float32, ``tri_color`` (T, 3, 3) float32 linear,
    ``tri_normal`` (T, 3) float64 unit (and ``tri_normal32``), ``tri_plane`` (T,) float64 (``n . p`` on the plane),
    ``tri_texel_density`` (T,) float32 texels per metre at mip level 0.
    """

    def __init__(self, parts: Sequence[MeshPart], overlays: Sequence[MeshPart] = (),
                 segments: Sequence[Segment] = ()) -> None:
        if not parts and not overlays:
            raise DataError("scene model: no meshes to render")
        all_parts = list(parts) + list(overlays)
        self.segments: dict[int, Segment] = {s.segment_id: s for s in segments}
        self.textures: list[Texture] = []
        offsets = np.cumsum([0] + [len(p.faces) for p in all_parts])
        self.n_triangles = int(offsets[-1])
        self._build_arrays(all_parts, offsets)
        self.atlas = TextureAtlas.build(self.textures)

        self.scene = o3d.t.geometry.RaycastingScene()
        self.geometry_offset = self._add_to_scene(self.scene, list(parts), offsets[: len(parts)])
        self.overlay_scene: o3d.t.geometry.RaycastingScene | None = None
        self.overlay_offset = np.zeros(0, dtype=np.int64)
        if overlays:
            self.overlay_scene = o3d.t.geometry.RaycastingScene()
            self.overlay_offset = self._add_to_scene(self.overlay_scene, list(overlays), offsets[len(parts): -1])
        self.has_geometry = bool(parts)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_spec(cls, spec: SceneSpec, include_board: bool = False, include_static: bool = True,
                  board_px_per_m: float = DEFAULT_BOARD_PX_PER_M) -> SceneModel:
        """Load the spec's objects (ids 1..K), static meshes and optionally the board."""
        if len(spec.objects) > MAX_OBJECTS:
            raise DataError(f"{spec.source}: at most {MAX_OBJECTS} objects are supported, got {len(spec.objects)}")
        parts: list[MeshPart] = []
        segments: list[Segment] = []

        def add(item: MeshSpec, segment_id: int, kind: SegmentKind) -> None:
            path = spec.resolve(item.mesh)
            parts.extend(load_mesh_parts(path, item.scale, item.pose.matrix(), segment_id, item.name))
            segments.append(Segment(segment_id, item.name, kind, str(path)))

        for i, obj in enumerate(spec.objects):
            add(obj, i + 1, "object")
        if include_static:
            for i, static in enumerate(spec.static_meshes):
                add(static, STATIC_ID_BASE + i, "static")
        overlays = []
        if include_board:
            overlays.append(board_part(spec.board, board_px_per_m))
            segments.append(Segment(BOARD_SEGMENT_ID, "charuco_board", "board", "<board>"))
        return cls(parts, overlays, segments)

    def _build_arrays(self, parts: list[MeshPart], offsets: NDArray[np.int64]) -> None:
        n = self.n_triangles
        self.tri_segment = np.zeros(n, dtype=np.int32)
        self.tri_texture = np.full(n, -1, dtype=np.int32)
        self.tri_uv = np.zeros((n, 3, 2), dtype=np.float32)
        self.tri_color = np.zeros((n, 3, 3), dtype=np.float32)
        self.tri_normal = np.zeros((n, 3), dtype=np.float64)
        self.tri_normal32 = np.zeros((n, 3), dtype=np.float32)
        self.tri_plane = np.zeros(n, dtype=np.float64)
        self.tri_texel_density = np.zeros(n, dtype=np.float32)
        for part, start in zip(parts, offsets[:-1]):
            sl = slice(int(start), int(start) + len(part.faces))
            corners = part.vertices[part.faces]  # (F, 3, 3)
            cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            area2 = np.linalg.norm(cross, axis=1)
            normal = np.where(area2[:, None] > 0, cross / np.maximum(area2, 1e-300)[:, None], (0.0, 0.0, 1.0))
            self.tri_normal[sl] = normal
            self.tri_normal32[sl] = normal
            self.tri_plane[sl] = np.einsum("ij,ij->i", normal, corners[:, 0])
            self.tri_segment[sl] = part.segment_id
            if part.texture is not None and part.uv is not None:
                tex = Texture.from_srgb(part.texture, part.source)
                self.tri_texture[sl] = len(self.textures)
                self.textures.append(tex)
                tri_uv = part.uv[part.faces]  # (F, 3, 2)
                self.tri_uv[sl] = tri_uv
                h, w = part.texture.shape[:2]
                e1 = tri_uv[:, 1] - tri_uv[:, 0]
                e2 = tri_uv[:, 2] - tri_uv[:, 0]
                duv = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
                texel_area2 = np.abs(duv) * w * h
                self.tri_texel_density[sl] = np.sqrt(texel_area2 / np.maximum(area2, 1e-300))
            elif part.vertex_colors is not None:
                self.tri_color[sl] = srgb_to_linear(part.vertex_colors)[part.faces]
            elif part.face_colors is not None:
                self.tri_color[sl] = np.repeat(srgb_to_linear(part.face_colors)[:, None, :], 3, axis=1)
            else:
                self.tri_color[sl] = srgb_to_linear(np.array(part.color, dtype=np.float32))

    @staticmethod
    def _add_to_scene(scene: o3d.t.geometry.RaycastingScene, parts: list[MeshPart],
                      starts: NDArray[np.int64]) -> NDArray[np.int64]:
        """Add parts as geometries; return the global triangle offset per geometry id."""
        geometry_offset = np.zeros(len(parts), dtype=np.int64)
        for part, start in zip(parts, starts):
            gid = scene.add_triangles(o3d.core.Tensor(part.vertices.astype(np.float32)),
                                      o3d.core.Tensor(part.faces.astype(np.uint32)))
            if gid >= len(geometry_offset):
                raise RuntimeError(f"unexpected Open3D geometry id {gid} for {part.source}")
            geometry_offset[gid] = start
        return geometry_offset

    # ------------------------------------------------------------------ queries
    @property
    def object_count(self) -> int:
        """K: object ids are 1..K."""
        return sum(1 for s in self.segments.values() if s.kind == "object")

    def cast(self, rays: NDArray[np.float32]) -> Hits:
        """First hits of (N, 6) float32 rays ``[ox, oy, oz, dx, dy, dz]`` (world frame).

        ``t`` is in units of the direction's length. Board (overlay) hits win over mesh hits
        that are at most :data:`BOARD_TIE_TOLERANCE_M` (in ``t`` units) closer.
        """
        n = len(rays)
        if self.has_geometry:
            t, triangle, bary = self._cast_one(self.scene, self.geometry_offset, rays)
        else:
            t = np.full(n, np.inf, dtype=np.float32)
            triangle = np.full(n, -1, dtype=np.int64)
            bary = np.zeros((n, 2), dtype=np.float32)
        if self.overlay_scene is not None:
            t_o, tri_o, bary_o = self._cast_one(self.overlay_scene, self.overlay_offset, rays)
            wins = np.isfinite(t_o) & (t_o <= t + np.float32(BOARD_TIE_TOLERANCE_M))
            t = np.where(wins, t_o, t)
            triangle = np.where(wins, tri_o, triangle)
            bary = np.where(wins[:, None], bary_o, bary)
        return Hits(hit=np.isfinite(t), triangle=triangle, bary=bary, t=t)

    @staticmethod
    def _cast_one(scene: o3d.t.geometry.RaycastingScene, geometry_offset: NDArray[np.int64],
                  rays: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.float32]]:
        out = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, dtype=np.float32)))
        t = out["t_hit"].numpy()
        geometry = out["geometry_ids"].numpy()
        primitive = out["primitive_ids"].numpy()
        hit = np.isfinite(t)
        safe_geometry = np.where(hit, geometry, 0)
        triangle = np.where(hit, np.take(geometry_offset, safe_geometry) + primitive, -1)
        return t, triangle, out["primitive_uvs"].numpy()
