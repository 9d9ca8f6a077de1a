"""Depth rasterisation by OpenGL's rules: the pixels and depths bop_toolkit's renderer draws.

bop_toolkit renders VSD's depth maps with OpenGL (``renderer_vispy``: a vertex shader, a 16-bit
depth buffer); on a machine without a GPU that is Mesa's llvmpipe. A ray cast through each pixel
centre decides pixels whose centre lies within a few thousandths of a pixel of a silhouette edge
differently from a rasteriser, and VSD's errors move by a pixel. This module follows the
pipeline instead, step by step, so both decide every pixel alike:

1. Vertex stage in float32: bop_toolkit's model-view-projection matrix (``_calc_calib_proj``, y
   down, near/far planes at the model's bounding box) built in float64 from the float32 pose and
   rounded to float32 (a uniform), each vertex transformed as GLSL's ``mat4 * vec4``, then
   draw_llvm's viewport: ``x * (1 / w)`` and a fused multiply-add (the CPU has FMA).
2. Clipping as Mesa's draw module does it (``draw_pipe_clip.c``): a triangle with a vertex outside
   the near, far or viewport planes (float32 tests on the clip coordinates) is cut by
   Sutherland-Hodgman in float32, its new vertices divided and mapped without FMA, and drawn as
   a fan. bop_toolkit's near plane is the nearest bounding-box corner, so the nearest vertex often
   lies a rounding error outside it and its triangles are cut there.
3. Window positions snapped to llvmpipe's sub-pixel grid: ``round((x - 0.5) * 256)`` (8 fractional
   bits, ``FIXED_ORDER``; pixel centres at +0.5; round to nearest even as SSE's cvtps does).
4. Coverage by exact integer edge functions with the top-left fill rule in the framebuffer's
   row order (bop_toolkit draws into an FBO, row 0 at the bottom: st/mesa leaves gallium's
   ``bottom_edge_rule`` at 0), as ``lp_setup_tri.c`` sets its planes: covered when all three > 0.
5. Depth: llvmpipe's plane setup (``lp_state_setup.c``: float32, relative to the framebuffer
   origin) and fragment interpolation (fused multiply-adds), converted to the 16-bit unorm of
   vispy's ``GL_DEPTH_COMPONENT16`` buffer as gallivm converts (``z * 65535/65536 + 128``), the
   nearest fragment kept (``GL_LESS``: the first triangle drawn wins a tie), read back as float32
   and turned into z-depth with bop_toolkit's float32 formula.

Measured against bop_toolkit's own renders (vispy 0.17 on Mesa 22.3.6 llvmpipe, 963 poses of the
demo's held-out split): every mask and every depth value equal (docs/BENCHMARKS.md). Poses
bop_toolkit cannot draw (a model reaching behind the camera: its near plane <= 0) get a near
plane of 1 µm, so depths stay finite and nothing behind the camera is drawn.
Units: millimetres; ``K`` in the project's convention (pixel centres at integers), so the BOP
file's ``cam_K`` is ``K`` with 0.5 added to ``cx`` and ``cy``.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

FIXED_ORDER = 8
"""llvmpipe's sub-pixel precision: 8 fractional bits (``lp_rast.h``)."""
FIXED_ONE = 1 << FIXED_ORDER
DEPTH_BITS = 16
"""vispy's depth renderbuffer (``GL_DEPTH_COMPONENT16``), the one bop_toolkit's renderer reads."""
_DEPTH_MAX = (1 << DEPTH_BITS) - 1
GUARD_BAND = 1.0
"""x/y clip planes at this many times the viewport's half-size: llvmpipe (Mesa 22.3) clips
triangles at the viewport itself (a guard band of 4096 draws one pixel differently)."""
_MIN_NEAR_MM = 1e-3
_Q_FINE = 1 << 53
"""Depth steps of the high-precision mode (window z in float64)."""


def bbox_corners(vertices: NDArray[np.float64]) -> NDArray[np.float64]:
    """The model's bounding-box corners as bop_toolkit computes them (``misc.calc_3d_bbox``)."""
    v = np.asarray(vertices, dtype=np.float64)
    lo = v.min(axis=0)
    size = v.max(axis=0) - lo
    return np.array([[lo[0] + a * size[0], lo[1] + b * size[1], lo[2] + c * size[2]]
                     for a in (0, 1) for b in (0, 1) for c in (0, 1)])


def gl_matrices(
    R: NDArray[np.float64], t: NDArray[np.float64], K: NDArray[np.float64], width: int, height: int,
    corners: NDArray[np.float64],
) -> tuple[NDArray[np.float32], float, float, bool]:
    """As bop_toolkit's vispy renderer builds them: the float32 model-view-projection applied as
    ``clip = M @ [x, y, z, 1]``, the near and far planes (mm); False when bop_toolkit's planes
    could not draw the model (then widened here)."""
    view_cv = np.eye(4, dtype=np.float32)
    view_cv[:3, :3], view_cv[:3, 3] = R, t
    flip = np.eye(4, dtype=np.float32)
    flip[1, 1], flip[2, 2] = -1, -1
    view_gl = flip.dot(view_cv)
    corners_ht = np.concatenate((corners, np.ones((len(corners), 1))), axis=1).T
    eye_z = view_cv[2, :].reshape((1, 4)).dot(corners_ht)
    near, far = float(eye_z.min()), float(eye_z.max())
    drawable = near > _MIN_NEAR_MM and far > near
    # Outside what bop_toolkit can draw (a model reaching behind the camera: near <= 0; a flat
    # model facing it: near == far) the depth range is widened, 1 mm or 0.1 % beyond the model
    # on both sides (bop_toolkit's planes run through its corners and may clip it there); a near
    # plane at or behind the camera moves to 1/1000 of far (geometry nearer is clipped away).
    if not drawable:
        margin = max(1.0, 1e-3 * abs(far))
        near = max(near - margin, 0.5 * near) if near > _MIN_NEAR_MM else max(_MIN_NEAR_MM, 1e-3 * far)
        far = max(far, near) + margin
    fx, fy, s = float(K[0, 0]), float(K[1, 1]), float(K[0, 1])
    cx, cy = float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5  # the BOP file's cam_K
    w, h = float(width), float(height)
    depth = float(far - near)
    q = -(far + near) / depth if depth != 0 else 0.0
    qn = -2 * (far * near) / depth if depth != 0 else 0.0
    proj = np.array([[2 * fx / w, -2 * s / w, (-2 * cx + w) / w, 0],
                     [0, 2 * fy / h, (2 * cy - h) / h, 0],
                     [0, 0, q, qn],
                     [0, 0, -1, 0]])
    # bop_toolkit: u_mvp = model @ view.T @ proj.T (row vectors), uploaded as float32 and read
    # column-major by GL, i.e. clip = (proj @ view_gl) @ v.
    mvp = np.dot(np.dot(np.eye(4, dtype=np.float32), view_gl.T), proj.T)
    return mvp.astype(np.float32).T.copy(), near, far, drawable


@njit(cache=True, error_model="numpy")
def _edge_setup(x: NDArray[np.int64], y: NDArray[np.int64], i: int, j: int) -> tuple[int, int, int]:
    """lp_setup_tri.c's plane of edge i -> j: (c, dcdx, dcdy), top-left rule's bias included."""
    dcdx = y[i] - y[j]
    dcdy = x[i] - x[j]
    c = dcdx * x[i] - dcdy * y[i]
    if dcdx < 0 or (dcdx == 0 and dcdy > 0):
        c += 1
    return c, dcdx, dcdy


@njit(cache=True, error_model="numpy")
def _unorm16(z: np.float32) -> int:
    """gallivm's lp_build_clamped_float_to_unsigned_norm for 16 bits: clamp to [0, 1] (NaN to 0),
    ``z * (65535 / 65536) + 128`` in float32, the mantissa's low 16 bits (round to nearest even)."""
    if not z > np.float32(0.0):
        z = np.float32(0.0)
    if z > np.float32(1.0):
        z = np.float32(1.0)
    r = np.float32(np.float32(z * np.float32(_DEPTH_MAX / (_DEPTH_MAX + 1.0))) + np.float32(1 << (23 - DEPTH_BITS)))
    return np.int64(np.array([r]).view(np.int32)[0] & _DEPTH_MAX)


@njit(cache=True, error_model="numpy")
def _raster_triangle(
    xs: NDArray[np.float32], ys: NDArray[np.float32], zs: NDArray[np.float32],
    zbuf: NDArray[np.int64], org: NDArray[np.int64], width: int, height: int, qmax: int, box: NDArray[np.int64],
) -> None:
    """One triangle (window x, y, z in float32, memory rows) into the z-buffer, GL_LESS.

    ``qmax`` 65535: llvmpipe's 16-bit depth in float32; otherwise window z interpolated in float64
    and stored as ``round(z * qmax)`` (poses bop_toolkit cannot draw, where 16 bits are too few)."""
    xf = np.empty(3, dtype=np.int64)
    yf = np.empty(3, dtype=np.int64)
    lim = np.float32(4 * (width + height + 2))  # clipped to the viewport: only a w near 0 goes far beyond
    for k in range(3):
        if not (abs(xs[k]) < lim and abs(ys[k]) < lim and np.isfinite(zs[k])):
            return
        # (v - pixel_offset) * FIXED_ONE in float32, rounded to nearest even (cvtps2dq).
        xf[k] = np.int64(np.rint(np.float32(xs[k] - np.float32(0.5)) * np.float32(FIXED_ONE)))
        yf[k] = np.int64(np.rint(np.float32(ys[k] - np.float32(0.5)) * np.float32(FIXED_ONE)))
    area = (xf[0] - xf[1]) * (yf[2] - yf[0]) - (xf[2] - xf[0]) * (yf[0] - yf[1])
    if area == 0:
        return
    if area < 0:  # rotate_fixed_position_01: draw as v1, v0, v2
        xf[0], xf[1] = xf[1], xf[0]
        yf[0], yf[1] = yf[1], yf[0]
    c0, dx0, dy0 = _edge_setup(xf, yf, 0, 1)
    c1, dx1, dy1 = _edge_setup(xf, yf, 1, 2)
    c2, dx2, dy2 = _edge_setup(xf, yf, 2, 0)
    # zbuf holds the pixels [org[0], org[0] + rows) x [org[1], org[1] + cols) of the framebuffer
    px0 = max((min(xf[0], xf[1], xf[2]) >> FIXED_ORDER) - 1, 0, org[1])
    px1 = min((max(xf[0], xf[1], xf[2]) >> FIXED_ORDER) + 1, width - 1, org[1] + zbuf.shape[1] - 1)
    py0 = max((min(yf[0], yf[1], yf[2]) >> FIXED_ORDER) - 1, 0, org[0])
    py1 = min((max(yf[0], yf[1], yf[2]) >> FIXED_ORDER) + 1, height - 1, org[0] + zbuf.shape[0] - 1)
    if px0 > px1 or py0 > py1:
        return
    # Depth plane as llvmpipe's setup (lp_state_setup.c, init_args + calc_coef4) computes it, in
    # float32, over the window positions in the order drawn, relative to the framebuffer origin.
    i0, i1 = (1, 0) if area < 0 else (0, 1)
    x0, y0, z0 = xs[i0], ys[i0], zs[i0]
    x1, y1, z1 = xs[i1], ys[i1], zs[i1]
    x2, y2, z2 = xs[2], ys[2], zs[2]
    half = np.float32(0.5)
    x0c = np.float32(x0 - half)
    y0c = np.float32(y0 - half)
    dx01 = np.float32(x0 - x1)
    dy01 = np.float32(y0 - y1)
    dx20 = np.float32(x2 - x0)
    dy20 = np.float32(y2 - y0)
    ooa = np.float32(np.float32(1.0) / np.float32(np.float32(dx01 * dy20) - np.float32(dy01 * dx20)))
    dx20o = np.float32(dx20 * ooa)
    dy20o = np.float32(dy20 * ooa)
    dx01o = np.float32(dx01 * ooa)
    dy01o = np.float32(dy01 * ooa)
    dz01 = np.float32(z0 - z1)
    dz20 = np.float32(z2 - z0)
    dzdx = np.float32(np.float32(dz01 * dy20o) - np.float32(dz20 * dy01o))
    dzdy = np.float32(np.float32(dz20 * dx01o) - np.float32(dz01 * dx20o))
    a0 = np.float32(z0 - np.float32(np.float32(dzdx * x0c) + np.float32(dzdy * y0c)))
    if not (np.isfinite(a0) and np.isfinite(dzdx) and np.isfinite(dzdy)):
        return
    # the same plane in float64, about the first vertex (the high-precision mode)
    x64_0, y64_0, z64_0 = np.float64(x0) - 0.5, np.float64(y0) - 0.5, np.float64(z0)
    e1x, e1y = np.float64(x1) - np.float64(x0), np.float64(y1) - np.float64(y0)
    e2x, e2y = np.float64(x2) - np.float64(x0), np.float64(y2) - np.float64(y0)
    det = e1x * e2y - e2x * e1y
    z64_dx = ((np.float64(z1) - z64_0) * e2y - (np.float64(z2) - z64_0) * e1y) / det
    z64_dy = ((np.float64(z2) - z64_0) * e1x - (np.float64(z1) - z64_0) * e2x) / det
    for py in range(py0, py1 + 1):
        Y = py << FIXED_ORDER
        for px in range(px0, px1 + 1):
            X = px << FIXED_ORDER
            if c0 - dx0 * X + dy0 * Y <= 0:
                continue
            if c1 - dx1 * X + dy1 * Y <= 0:
                continue
            if c2 - dx2 * X + dy2 * Y <= 0:
                continue
            if qmax == _DEPTH_MAX:
                # fragment z: fmuladd(dady, y, fmuladd(dadx, x, a0)), fused (see _window on float64)
                z = np.float32(np.float64(np.float32(np.float64(dzdx) * px + np.float64(a0))) + np.float64(dzdy) * py)
                q = _unorm16(z)
            else:
                z64 = z64_0 + z64_dx * (px - x64_0) + z64_dy * (py - y64_0)
                q = np.int64(np.rint(min(max(z64, 0.0), 1.0) * qmax)) if np.isfinite(z64) else qmax
            if q < zbuf[py - org[0], px - org[1]]:
                zbuf[py - org[0], px - org[1]] = q
                box[0] = min(box[0], py)
                box[1] = max(box[1], py)
                box[2] = min(box[2], px)
                box[3] = max(box[3], px)


@njit(cache=True, error_model="numpy")
def _window(clip: NDArray[np.float32], width: int, height: int) -> tuple[np.float32, np.float32, np.float32]:
    """Perspective divide and viewport transform in float32 as draw_llvm's generate_viewport:
    ``x * (1 / w)``, then ``fmuladd(x, scale, translate)``, fused on a CPU with FMA (one rounding).
    Here through float64: the float32 product is exact there, the sum rounds to float64 and then to
    float32, which differs from one rounding only when the first rounding makes a float32 tie."""
    inv_w = np.float32(1.0) / clip[3]
    half_w = np.float64(np.float32(width * 0.5))
    half_h = np.float64(np.float32(height * 0.5))
    x = np.float32(np.float64(np.float32(clip[0] * inv_w)) * half_w + half_w)
    y = np.float32(np.float64(np.float32(clip[1] * inv_w)) * half_h + half_h)
    z = np.float32(np.float64(np.float32(clip[2] * inv_w)) * 0.5 + 0.5)
    return x, y, z


_PLANES = np.array([[-1.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 1.0],
                    [0.0, 1.0, 0.0, 1.0], [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, -1.0, 1.0]], dtype=np.float32)
"""The draw module's view-volume planes (``draw_context.c``): x <= w, -w <= x, y <= w, -w <= y, near, far."""


@njit(cache=True, error_model="numpy")
def _clipmask(c: NDArray[np.float32], guard: np.float32) -> int:
    """draw_llvm's generate_clipmask in float32: bits 0-3 x/y (here against the guard band), 4 near, 5 far."""
    m = 0
    gw = np.float32(c[3] * guard)
    if c[0] > gw:
        m |= 1
    if np.float32(0.0) > np.float32(c[0] + gw):
        m |= 2
    if c[1] > gw:
        m |= 4
    if np.float32(0.0) > np.float32(c[1] + gw):
        m |= 8
    if np.float32(0.0) > np.float32(c[2] + c[3]):
        m |= 16
    if c[2] > c[3]:
        m |= 32
    if not (np.isfinite(c[0]) and np.isfinite(c[1]) and np.isfinite(c[2]) and np.isfinite(c[3])):
        m |= 64
    return m


@njit(cache=True, error_model="numpy")
def _plane_dist(c: NDArray[np.float32], p: int, guard: np.float32) -> np.float32:
    """draw_pipe_clip's dot4(clip_pos, plane) in float32 (the x/y planes scaled to the guard band)."""
    w = c[3]
    if p < 4:
        w = np.float32(w * guard)
    pl = _PLANES[p]
    return np.float32(np.float32(np.float32(np.float32(c[0] * pl[0]) + np.float32(c[1] * pl[1]))
                                 + np.float32(c[2] * pl[2])) + np.float32(w * pl[3]))


@njit(cache=True, error_model="numpy")
def _interp(t: np.float32, cout: NDArray[np.float32], cin: NDArray[np.float32],
            width: int, height: int, dst_clip: NDArray[np.float32], dst_win: NDArray[np.float32]) -> None:
    """draw_pipe_clip's interp(): LINTERP of the clip position, then divide and viewport in C float32 (no FMA)."""
    for k in range(4):
        dst_clip[k] = np.float32(cout[k] + np.float32(t * np.float32(cin[k] - cout[k])))
    oow = np.float32(np.float32(1.0) / dst_clip[3])
    half_w = np.float32(width * 0.5)
    half_h = np.float32(height * 0.5)
    dst_win[0] = np.float32(np.float32(np.float32(dst_clip[0] * oow) * half_w) + half_w)
    dst_win[1] = np.float32(np.float32(np.float32(dst_clip[1] * oow) * half_h) + half_h)
    dst_win[2] = np.float32(np.float32(np.float32(dst_clip[2] * oow) * np.float32(0.5)) + np.float32(0.5))


@njit(cache=True, error_model="numpy")
def _clip_triangle(
    clip3: NDArray[np.float32], win3: NDArray[np.float32], clipmask: int, guard: np.float32,
    width: int, height: int, zbuf: NDArray[np.int64], org: NDArray[np.int64], qmax: int, box: NDArray[np.int64],
) -> None:
    """draw_pipe_clip's do_clip_tri: Sutherland-Hodgman over the planes in ``clipmask``, drawn as a fan."""
    cap = 3 + 2 * 6 + 1
    n_clip = np.empty((2 * cap, 4), dtype=np.float32)  # vertex pool: 3 originals then new ones
    n_win = np.empty((2 * cap, 3), dtype=np.float32)
    n_clip[:3] = clip3
    n_win[:3] = win3
    pool = 3
    inl = np.empty(cap, dtype=np.int64)
    outl = np.empty(cap, dtype=np.int64)
    inl[0], inl[1], inl[2] = 0, 1, 2
    n = 3
    for p in range(6):
        if not (clipmask >> p) & 1 or n < 3:
            continue
        vprev = inl[0]
        dp_prev = _plane_dist(n_clip[vprev], p, guard)
        if not np.isfinite(dp_prev):
            return
        inl[n] = inl[0]
        outc = 0
        for i in range(1, n + 1):
            v = inl[i]
            dp = _plane_dist(n_clip[v], p, guard)
            if not np.isfinite(dp):
                return
            if dp_prev >= np.float32(0.0):
                outl[outc] = vprev
                outc += 1
                different = dp < np.float32(0.0)
            else:
                different = not (dp < np.float32(0.0))
            if different:
                if pool >= 2 * cap or outc >= cap:
                    return
                nv = pool
                pool += 1
                denom = np.float32(dp - dp_prev)
                # interp(t, out, in) as draw_pipe_clip chooses it (the same t either way round)
                if dp < np.float32(0.0):
                    flip = not (-dp < dp_prev)
                    t = np.float32(-dp_prev / denom) if flip else np.float32(dp / denom)
                else:
                    flip = -dp_prev < dp
                    t = np.float32(-dp_prev / denom) if flip else np.float32(dp / denom)
                a, b = (vprev, v) if flip else (v, vprev)
                _interp(t, n_clip[a], n_clip[b], width, height, n_clip[nv], n_win[nv])
                outl[outc] = nv
                outc += 1
            vprev = v
            dp_prev = dp
        for i in range(outc):
            inl[i] = outl[i]
        n = outc
    xs = np.empty(3, dtype=np.float32)
    ys = np.empty(3, dtype=np.float32)
    zs = np.empty(3, dtype=np.float32)
    for i in range(2, n):  # emit_poly, provoking vertex last: (i-1, i, 0)
        for k, vi in enumerate((inl[i - 1], inl[i], inl[0])):
            xs[k], ys[k], zs[k] = n_win[vi, 0], n_win[vi, 1], n_win[vi, 2]
        _raster_triangle(xs, ys, zs, zbuf, org, width, height, qmax, box)


@njit(cache=True, error_model="numpy")
def _raster_mesh(
    verts: NDArray[np.float32], faces: NDArray[np.int64], mvp: NDArray[np.float32], guard: np.float32,
    width: int, height: int, zbuf: NDArray[np.int64], org: NDArray[np.int64], qmax: int, box: NDArray[np.int64],
) -> None:
    """Every face, in index order, into ``zbuf``: vertex shader, clip test, clipping, setup, rasterisation."""
    nv = verts.shape[0]
    clip = np.empty((nv, 4), dtype=np.float32)
    win = np.empty((nv, 3), dtype=np.float32)
    mask = np.empty(nv, dtype=np.int64)
    for k in range(nv):
        x, y, z = verts[k, 0], verts[k, 1], verts[k, 2]
        for r in range(4):  # GLSL mat * vec: col0 * x + col1 * y + col2 * z + col3
            acc = np.float32(mvp[r, 0] * x)
            acc = np.float32(acc + np.float32(mvp[r, 1] * y))
            acc = np.float32(acc + np.float32(mvp[r, 2] * z))
            clip[k, r] = np.float32(acc + mvp[r, 3])
        mask[k] = _clipmask(clip[k], guard)
        if mask[k] == 0:
            win[k, 0], win[k, 1], win[k, 2] = _window(clip[k], width, height)
        else:
            win[k, 0], win[k, 1], win[k, 2] = np.float32(0.0), np.float32(0.0), np.float32(0.0)
    xs = np.empty(3, dtype=np.float32)
    ys = np.empty(3, dtype=np.float32)
    zs = np.empty(3, dtype=np.float32)
    clip3 = np.empty((3, 4), dtype=np.float32)
    win3 = np.empty((3, 3), dtype=np.float32)
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        m_or = mask[a] | mask[b] | mask[c]
        if m_or == 0:
            for k, vi in enumerate((a, b, c)):
                xs[k], ys[k], zs[k] = win[vi, 0], win[vi, 1], win[vi, 2]
            _raster_triangle(xs, ys, zs, zbuf, org, width, height, qmax, box)
            continue
        if (mask[a] & mask[b] & mask[c]) != 0 or (m_or & 64) != 0:
            continue  # all outside one plane, or not finite
        for k, vi in enumerate((a, b, c)):
            clip3[k] = clip[vi]
            # the originals keep the vertex shader's window position (finite only when inside)
            if mask[vi] == 0:
                win3[k] = win[vi]
            else:
                win3[k, 0], win3[k, 1], win3[k, 2] = _window(clip[vi], width, height)
        _clip_triangle(clip3, win3, m_or, guard, width, height, zbuf, org, qmax, box)


def _window_box(
    v32: NDArray[np.float32], R: NDArray[np.float64], t: NDArray[np.float64], K: NDArray[np.float64], w: int, h: int,
) -> tuple[NDArray[np.int64], int, int]:
    """A framebuffer window (origin row, col; rows; cols) that holds every pixel the mesh can cover:
    its projected vertices' box and 2 px, or the whole image when a vertex is not in front."""
    cam = v32.astype(np.float64) @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64).reshape(3)
    z = cam[:, 2]
    if not (np.all(np.isfinite(cam)) and np.all(z > _MIN_NEAR_MM)):
        return np.zeros(2, dtype=np.int64), h, w
    u = K[0, 0] * cam[:, 0] / z + K[0, 1] * cam[:, 1] / z + K[0, 2]
    v = K[1, 1] * cam[:, 1] / z + K[1, 2]
    c0 = int(np.clip(np.floor(u.min()) - 2, 0, w))
    c1 = int(np.clip(np.ceil(u.max()) + 3, 0, w))
    r0 = int(np.clip(np.floor(h - 1 - v.max()) - 2, 0, h))  # framebuffer rows run bottom-up
    r1 = int(np.clip(np.ceil(h - 1 - v.min()) + 3, 0, h))
    if c1 <= c0 or r1 <= r0:
        return np.zeros(2, dtype=np.int64), 1, 1
    return np.array([r0, c0], dtype=np.int64), r1 - r0, c1 - c0


def gl_depth(
    vertices: NDArray[np.float64], faces: NDArray[np.int64], corners: NDArray[np.float64],
    R: NDArray[np.float64], t: NDArray[np.float64], K: NDArray[np.float64], width: int, height: int,
) -> NDArray[np.float64]:
    """Z-depth image (height, width) in mm, 0 = background, as bop_toolkit's vispy renderer on llvmpipe draws it.

    ``corners`` are :func:`bbox_corners` of the model (bop_toolkit's near and far planes);
    ``K`` in the project's convention (pixel centres at integers).
    """
    w, h = int(width), int(height)
    mvp, near, far, parity = gl_matrices(R, t, K, w, h, corners)
    qmax = _DEPTH_MAX if parity else _Q_FINE
    v32 = np.asarray(vertices, dtype=np.float32)
    org, rows, cols = _window_box(v32, R, t, K, w, h)
    zbuf = np.full((rows, cols), qmax, dtype=np.int64)
    box = np.array([h, -1, w, -1], dtype=np.int64)  # rows, columns drawn: min, max
    _raster_mesh(v32, np.ascontiguousarray(faces, dtype=np.int64), mvp, np.float32(GUARD_BAND), w, h, zbuf, org,
                 qmax, box)
    out = np.zeros((h, w), dtype=np.float64)
    if box[1] < 0:
        return out
    r0, r1, c0, c1 = int(box[0]), int(box[1]) + 1, int(box[2]), int(box[3]) + 1
    q = zbuf[r0 - org[0]:r1 - org[0], c0 - org[1]:c1 - org[1]]
    drawn = q < qmax
    if parity:  # read back (GL_FLOAT from a 16-bit unorm) and bop_toolkit's conversion, in float32 as there
        zwin = q.astype(np.float32) * np.float32(1.0 / _DEPTH_MAX)
        mult, addi = np.float32((near * far) / (near - far)), np.float32(far / (near - far))
    else:
        zwin = q / float(qmax)
        mult, addi = (near * far) / (near - far), far / (near - far)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dep = mult / (zwin + addi)
    # memory rows run bottom-up, as glReadPixels returns them; bop_toolkit flips them
    out[h - r1:h - r0, c0:c1] = np.where(drawn & np.isfinite(dep), dep, 0.0)[::-1]
    return out


def triangle_coverage(xy: NDArray[np.floating], width: int, height: int) -> NDArray[np.bool_]:
    """Pixels (rows as the framebuffer stores them, row 0 first) one triangle covers, given its
    three window positions (x, y) in pixels: snapped, edge functions and fill rule as in :func:`gl_depth`."""
    p = np.asarray(xy, dtype=np.float32).reshape(3, 2)
    zbuf = np.full((int(height), int(width)), _DEPTH_MAX, dtype=np.int64)
    box = np.array([height, -1, width, -1], dtype=np.int64)
    _raster_triangle(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]),
                     np.full(3, 0.5, dtype=np.float32), zbuf, np.zeros(2, dtype=np.int64), int(width), int(height),
                     _DEPTH_MAX, box)
    return zbuf < _DEPTH_MAX
