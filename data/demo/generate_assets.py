"""Regenerate the demo scene's meshes and textures (deterministic; the outputs are shipped).

Run from the repository root:  python data/demo/generate_assets.py
The scene spec that places these meshes is ``data/demo/scene.yaml`` (written by hand).

Objects are small, like the paper's "small" objects (under 32x32 px at 50 cm for a 640 px,
70 deg camera, i.e. under about 3.5 cm): a hex nut (industry), an espresso cup (household),
a sample vial (laboratory) and a toy brick (toys/office). Objects are PLY with vertex colours
in millimetres (scale 0.001 in the spec, as BOP models are); the table, the wall and the
clutter are OBJ files with a PNG texture, in metres.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import trimesh

OUT = Path(__file__).resolve().parent / "meshes"
RNG = np.random.default_rng(20261122)


# ----------------------------------------------------------------------------- textures
def _value_noise(h: int, w: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise in [0, 1]: random grid upsampled bicubically."""
    grid = rng.random((cells + 3, cells + 3)).astype(np.float32)
    big = cv2.resize(grid, (w + 3 * w // cells, h + 3 * h // cells), interpolation=cv2.INTER_CUBIC)
    return np.clip(big[:h, :w], 0.0, 1.0)


def table_texture(size: int = 1024) -> np.ndarray:
    """Wood-like table mat with printed shapes and labels: texture for features and 3DGS."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    noise = _value_noise(size, size, 24, RNG)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (x * 18 + 1.5 * noise + 0.4 * _value_noise(size, size, 6, RNG)))
    base = np.stack([150 + 60 * grain, 105 + 45 * grain, 60 + 30 * grain], axis=-1)
    base += (_value_noise(size, size, 96, RNG)[..., None] - 0.5) * 40
    img = np.clip(base, 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(img[:, :, ::-1])  # draw in BGR with OpenCV, convert back below
    for _ in range(140):
        colour = tuple(int(c) for c in RNG.integers(20, 235, 3))
        cx, cy = (int(v) for v in RNG.integers(0, size, 2))
        kind = RNG.integers(0, 4)
        if kind == 0:
            cv2.circle(img, (cx, cy), int(RNG.integers(4, 22)), colour, -1, cv2.LINE_AA)
        elif kind == 1:
            w, h = (int(v) for v in RNG.integers(6, 40, 2))
            cv2.rectangle(img, (cx, cy), (cx + w, cy + h), colour, -1, cv2.LINE_AA)
        elif kind == 2:
            pts = RNG.integers(-25, 25, (3, 2)) + np.array([cx, cy])
            cv2.fillConvexPoly(img, pts.astype(np.int32), colour, cv2.LINE_AA)
        else:
            text = "".join(chr(c) for c in RNG.integers(65, 91, int(RNG.integers(2, 6))))
            cv2.putText(img, text, (cx, cy), cv2.FONT_HERSHEY_SIMPLEX, float(RNG.uniform(0.4, 1.1)),
                        colour, int(RNG.integers(1, 3)), cv2.LINE_AA)
    return np.ascontiguousarray(img[:, :, ::-1])


def poster_texture(width: int, height: int, title: str) -> np.ndarray:
    """A wall poster / book cover: colour blocks, stripes and text."""
    img = np.full((height, width, 3), 235, np.uint8)
    img[:] = (np.array([220, 225, 232]) + (_value_noise(height, width, 8, RNG)[..., None] - 0.5) * 30).clip(0, 255)
    for _ in range(25):
        colour = tuple(int(c) for c in RNG.integers(30, 220, 3))
        x0, y0 = int(RNG.integers(0, width - 20)), int(RNG.integers(0, height - 20))
        w, h = int(RNG.integers(10, width // 3)), int(RNG.integers(10, height // 3))
        cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), colour, -1, cv2.LINE_AA)
    for i in range(8):
        colour = tuple(int(c) for c in RNG.integers(0, 120, 3))
        cv2.putText(img, title if i == 0 else "".join(chr(c) for c in RNG.integers(65, 91, 7)),
                    (int(RNG.integers(5, width // 3)), int(20 + i * height / 8)), cv2.FONT_HERSHEY_DUPLEX,
                    float(RNG.uniform(0.5, 1.2)), colour, 1, cv2.LINE_AA)
    return img


# ----------------------------------------------------------------------------- textured OBJ
def textured_box(size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box centred at the origin as 6 quads with their own vertices; the +z face maps the
    whole texture (u along +x, v along +y), the other faces map a thin strip of it."""
    sx, sy, sz = (s / 2 for s in size)
    faces_spec = [
        # (normal axis corners ccw seen from outside)
        [(-sx, -sy, sz), (sx, -sy, sz), (sx, sy, sz), (-sx, sy, sz)],  # top
        [(-sx, sy, -sz), (sx, sy, -sz), (sx, -sy, -sz), (-sx, -sy, -sz)],  # bottom
        [(-sx, -sy, -sz), (sx, -sy, -sz), (sx, -sy, sz), (-sx, -sy, sz)],  # -y
        [(sx, sy, -sz), (-sx, sy, -sz), (-sx, sy, sz), (sx, sy, sz)],  # +y
        [(sx, -sy, -sz), (sx, sy, -sz), (sx, sy, sz), (sx, -sy, sz)],  # +x
        [(-sx, sy, -sz), (-sx, -sy, -sz), (-sx, -sy, sz), (-sx, sy, sz)],  # -x
    ]
    verts, uvs, faces = [], [], []
    for i, quad in enumerate(faces_spec):
        base = len(verts)
        verts.extend(quad)
        if i == 0:
            uvs.extend([(0, 0), (1, 0), (1, 1), (0, 1)])
        else:
            uvs.extend([(0, 0), (1, 0), (1, 0.05), (0, 0.05)])
        faces.extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])
    return np.array(verts, float), np.array(uvs, float), np.array(faces, int)


def write_obj(path: Path, verts: np.ndarray, uvs: np.ndarray, faces: np.ndarray, texture: np.ndarray) -> None:
    """Write OBJ + MTL + PNG (same stem). Texture v=0 is the bottom row of the image (OBJ rule)."""
    stem = path.stem
    lines = [f"mtllib {stem}.mtl", f"o {stem}"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uvs]
    lines.append(f"usemtl {stem}")
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    path.with_suffix(".mtl").write_text(
        f"newmtl {stem}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {stem}.png\n")
    cv2.imwrite(str(path.with_suffix(".png")), texture[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])


# ----------------------------------------------------------------------------- objects (mm)
def _colour(mesh: trimesh.Trimesh, rgb: tuple[int, int, int]) -> trimesh.Trimesh:
    mesh.visual.vertex_colors = np.tile(np.array([*rgb, 255], np.uint8), (len(mesh.vertices), 1))
    return mesh


def hex_nut() -> trimesh.Trimesh:
    """M16-like nut: 24 mm across corners, 13 mm thick, 14 mm hole; z up, base at z=0."""
    nut = trimesh.creation.annulus(r_min=7.0, r_max=12.0, height=13.0, sections=6)
    nut.apply_translation([0, 0, 6.5])
    nut = _colour(nut, (150, 155, 165))
    shade = 0.75 + 0.25 * (nut.vertices[:, 2] / 13.0)
    nut.visual.vertex_colors[:, :3] = (np.array([150, 155, 165]) * shade[:, None]).astype(np.uint8)
    return nut


def espresso_cup() -> trimesh.Trimesh:
    """Cup 22 mm wide, 24 mm tall, with a handle; red with a white rim band."""
    body = trimesh.creation.cylinder(radius=11.0, height=24.0, sections=48)
    body.apply_translation([0, 0, 12.0])
    handle = trimesh.creation.torus(major_radius=5.0, minor_radius=1.6, major_sections=24, minor_sections=12)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([13.5, 0, 13.0])
    cup = trimesh.util.concatenate([body, handle])
    colours = np.tile(np.array([190, 30, 35, 255], np.uint8), (len(cup.vertices), 1))
    colours[cup.vertices[:, 2] > 20.0] = (245, 245, 240, 255)
    cup.visual.vertex_colors = colours
    return cup


def sample_vial() -> trimesh.Trimesh:
    """Vial 12 mm wide, 30 mm tall: translucent-blue body and an orange cap (lying on its side)."""
    body = trimesh.creation.cylinder(radius=6.0, height=22.0, sections=40)
    body.apply_translation([0, 0, 11.0])
    cap = trimesh.creation.cylinder(radius=6.6, height=8.0, sections=40)
    cap.apply_translation([0, 0, 26.0])
    vial = trimesh.util.concatenate([body, cap])
    colours = np.tile(np.array([120, 170, 215, 255], np.uint8), (len(vial.vertices), 1))
    colours[vial.vertices[:, 2] > 22.0] = (240, 140, 20, 255)
    vial.visual.vertex_colors = colours
    return vial


def toy_brick() -> trimesh.Trimesh:
    """2x2 toy brick: 16 x 16 x 11.4 mm with four studs; yellow."""
    parts = [trimesh.creation.box(extents=[16.0, 16.0, 11.4])]
    parts[0].apply_translation([0, 0, 5.7])
    for sx in (-4.0, 4.0):
        for sy in (-4.0, 4.0):
            stud = trimesh.creation.cylinder(radius=2.4, height=1.8, sections=24)
            stud.apply_translation([sx, sy, 11.4 + 0.9])
            parts.append(stud)
    brick = trimesh.util.concatenate(parts)
    colours = np.tile(np.array([245, 200, 20, 255], np.uint8), (len(brick.vertices), 1))
    colours[brick.vertices[:, 2] < 1.0] = (200, 160, 10, 255)
    brick.visual.vertex_colors = colours
    return brick


def clutter_block(size_mm: tuple[float, float, float], rgb: tuple[int, int, int]) -> trimesh.Trimesh:
    """Plain coloured block (clutter), base at z=0, in millimetres."""
    block = trimesh.creation.box(extents=size_mm)
    block.apply_translation([0, 0, size_mm[2] / 2])
    colours = np.tile(np.array([*rgb, 255], np.uint8), (len(block.vertices), 1))
    colours[block.vertices[:, 2] > size_mm[2] / 2] = np.clip(np.array(rgb) * 1.15, 0, 255).astype(np.uint8).tolist() + [255]
    block.visual.vertex_colors = colours
    return block


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    # static, textured, metres; the mesh frame is the box centre
    write_obj(OUT / "table.obj", *textured_box((0.80, 1.00, 0.03)), table_texture(1024))
    write_obj(OUT / "wall.obj", *textured_box((1.60, 0.80, 0.02)), poster_texture(768, 384, "BRAVE-6D LAB"))
    write_obj(OUT / "book.obj", *textured_box((0.15, 0.21, 0.02)), poster_texture(256, 358, "ROBOTICS"))
    write_obj(OUT / "notepad.obj", *textured_box((0.10, 0.14, 0.008)), poster_texture(200, 280, "NOTES"))
    # objects and clutter in millimetres, base on z=0
    for name, mesh in {
        "hex_nut": hex_nut(),
        "espresso_cup": espresso_cup(),
        "sample_vial": sample_vial(),
        "toy_brick": toy_brick(),
        "block_green": clutter_block((40.0, 25.0, 30.0), (60, 150, 70)),
        "block_blue": clutter_block((30.0, 30.0, 45.0), (50, 80, 170)),
    }.items():
        mesh.export(OUT / f"{name}.ply", encoding="binary")
    print(f"wrote assets to {OUT}")


if __name__ == "__main__":
    main()
