"""Numba kernels of the CPU rasterizer: projection, SH, tile binning, compositing, and
their backward passes.

Conventions follow gsplat 1.5.3's CUDA kernels (ProjectionEWA3DGSFused.cu,
RasterizeToPixels3DGSFwd/Bwd.cu, SphericalHarmonicsCUDA.cu, IntersectTile.cu):

* EWA projection with the Jacobian's x/z, y/z clamped to the image plus 30 % of the
  half field of view, ``eps2d`` added to the 2D covariance diagonal, opacity-aware
  bounding box of at most 3.33 sigma, Gaussians outside ``[near, far]`` culled.
* 16 px tiles, front-to-back compositing in depth order, ``alpha = min(0.999,
  o * exp(-sigma))``, skipped below 1/255, a pixel stops before the Gaussian that would
  bring its transmittance to <= 1e-4, backward by reverse traversal recovering T by
  division, exactly as gsplat's CUDA backward.

Per-Gaussian work (projection, SH) runs in float64 internally so that needle-thin or
huge Gaussians stay finite; per-pixel work runs in float32 like gsplat, with a
vectorisable exp and FMA contraction (as nvcc compiles gsplat) but no other fast-math.
Binning drops the tiles of a Gaussian's bounding box that its {alpha >= 1/255} ellipse
cannot reach and records, per intersection, the rows of the tile it can reach (a
conservative test, so results equal testing every pixel); compositing also skips rows whose
pixels have all stopped (forward) or lie behind every pixel's last contributor (backward).
Outputs are float32.  Parallelism: ``prange`` over Gaussians for projection / SH / binning
and workers taking tiles from a shared counter for compositing; the backward pass writes one
gradient row per intersection and sums each Gaussian's rows in tile order, so there are no
races and results do not depend on the number of threads.

All kernels are compiled with ``cache=True`` (on-disk cache next to this file), so the
JIT cost is paid once per machine.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from .constants import (
    ALPHA_MAX,
    ALPHA_THRESHOLD,
    DEPTH_ALPHA_EPS,
    QUAT_MIN_SQNORM,
    RADIUS_EXTEND,
    RADIUS_MAX,
    T_MIN,
    TILE_SIZE,
)

_F32 = np.float32
_F0 = np.float32(0.0)
_F05 = np.float32(0.5)
_F1 = np.float32(1.0)
_FALPHA_MAX = np.float32(ALPHA_MAX)
_FALPHA_THR = np.float32(ALPHA_THRESHOLD)
_FT_MIN = np.float32(T_MIN)
_FEXTEND = np.float32(RADIUS_EXTEND)
_FDEPTH_EPS = np.float32(DEPTH_ALPHA_EPS)
_F32_MAX = 3.0e38
_TS = TILE_SIZE
_TP = TILE_SIZE * TILE_SIZE
_BLOCK = 256  # Gaussians per parallel work item in per-Gaussian kernels
_N_GRAD = 12  # per-Gaussian compositing grads: xy(2) conic(3) opacity(1) colour(4) |xy|(2)
# The per-pixel kernels allow LLVM to fuse a * b + c into one FMA ('contract'), as nvcc does
# by default for gsplat's CUDA kernels; no other fast-math assumption (NaN/inf, reassociation,
# approximate functions) is made.
_PIXEL_MATH = {"contract"}

_SH_C0 = 0.28209479177387814
_SH_C1 = 0.48860251190292


# --------------------------------------------------------------------------------------
# Vectorisable float32 exp
# --------------------------------------------------------------------------------------
# libm's expf is an opaque call that stops LLVM from vectorising the per-pixel loops.
# This is the Cephes expf scheme (Cody-Waite reduction + degree-6 polynomial), accurate to
# about 1 ulp like libm; 2^n is built by writing the exponent bits directly.

_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_EP0 = np.float32(1.9875691500e-4)
_EP1 = np.float32(1.3981999507e-3)
_EP2 = np.float32(8.3334519073e-3)
_EP3 = np.float32(4.1665795894e-2)
_EP4 = np.float32(1.6666665459e-1)
_EP5 = np.float32(5.0000001201e-1)
_EXP_ARG_MAX = np.float32(87.0)


@intrinsic
def _int32_bits_as_float32(typingctx, x):
    """Reinterpret the bits of an int32 as a float32 (LLVM bitcast)."""
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


@intrinsic
def _atomic_fetch_add(typingctx, counter, value):
    """Atomically add ``value`` to ``counter[0]`` (an int64 array); return the old value."""
    sig = types.int64(counter, types.int64)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, signature.args[0], ary,
                                       [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", ptr, args[1], "monotonic")

    return sig, codegen


@intrinsic
def _float32_bits_as_int32(typingctx, x):
    """Reinterpret the bits of a float32 as an int32 (LLVM bitcast)."""
    sig = types.int32(types.float32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return sig, codegen


@njit(cache=True, inline="always")
def exp_neg(s):
    """exp(-s) in float32 for s >= 0 (s is clamped to 87, exp(-87) ~ 1.6e-38)."""
    x = -min(s, _EXP_ARG_MAX)
    n = np.int32(x * _LOG2E - _F05)  # x <= 0: truncation rounds to nearest
    fn = _F32(n)
    x = x - fn * _LN2_HI - fn * _LN2_LO
    z = x * x
    y = ((((_EP0 * x + _EP1) * x + _EP2) * x + _EP3) * x + _EP4) * x + _EP5
    y = y * z + x + _F1
    return y * _int32_bits_as_float32((n + np.int32(127)) << np.int32(23))

# --------------------------------------------------------------------------------------
# Small float64 helpers (tuples: no heap allocation inside prange loops)
# --------------------------------------------------------------------------------------


@njit(cache=True)
def _quat_rotmat(w, x, y, z):
    """Rotation matrix (row-major 9-tuple) of a quaternion, normalised here.

    Returns (R, inv_norm, qn) where qn is the normalised quaternion.  A quaternion with
    squared norm below QUAT_MIN_SQNORM maps to the identity (inv_norm = 0).
    """
    n2 = w * w + x * x + y * y + z * z
    if not (n2 >= QUAT_MIN_SQNORM):
        return (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 0.0, (1.0, 0.0, 0.0, 0.0)
    inv = 1.0 / math.sqrt(n2)
    w *= inv
    x *= inv
    y *= inv
    z *= inv
    r = (
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )
    return r, inv, (w, x, y, z)


@njit(cache=True)
def _covar3d(q, s):
    """World covariance (row-major 9-tuple) Sigma = (R S)(R S)^T and the factors R, M."""
    r, inv, qn = _quat_rotmat(np.float64(q[0]), np.float64(q[1]), np.float64(q[2]), np.float64(q[3]))
    s0 = np.float64(s[0])
    s1 = np.float64(s[1])
    s2 = np.float64(s[2])
    m = (
        r[0] * s0, r[1] * s1, r[2] * s2,
        r[3] * s0, r[4] * s1, r[5] * s2,
        r[6] * s0, r[7] * s1, r[8] * s2,
    )
    cov = _mmt(m)
    return cov, r, m, inv, qn


@njit(cache=True)
def _mmt(m):
    """M @ M^T for a row-major 3x3 tuple."""
    return (
        m[0] * m[0] + m[1] * m[1] + m[2] * m[2],
        m[0] * m[3] + m[1] * m[4] + m[2] * m[5],
        m[0] * m[6] + m[1] * m[7] + m[2] * m[8],
        m[3] * m[0] + m[4] * m[1] + m[5] * m[2],
        m[3] * m[3] + m[4] * m[4] + m[5] * m[5],
        m[3] * m[6] + m[4] * m[7] + m[5] * m[8],
        m[6] * m[0] + m[7] * m[1] + m[8] * m[2],
        m[6] * m[3] + m[7] * m[4] + m[8] * m[5],
        m[6] * m[6] + m[7] * m[7] + m[8] * m[8],
    )


@njit(cache=True)
def _mm(a, b):
    """A @ B for row-major 3x3 tuples."""
    return (
        a[0] * b[0] + a[1] * b[3] + a[2] * b[6],
        a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
        a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
        a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
        a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
        a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[3] + a[8] * b[6],
        a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
        a[6] * b[2] + a[7] * b[5] + a[8] * b[8],
    )


@njit(cache=True)
def _mtm(a, b):
    """A^T @ B for row-major 3x3 tuples."""
    return (
        a[0] * b[0] + a[3] * b[3] + a[6] * b[6],
        a[0] * b[1] + a[3] * b[4] + a[6] * b[7],
        a[0] * b[2] + a[3] * b[5] + a[6] * b[8],
        a[1] * b[0] + a[4] * b[3] + a[7] * b[6],
        a[1] * b[1] + a[4] * b[4] + a[7] * b[7],
        a[1] * b[2] + a[4] * b[5] + a[7] * b[8],
        a[2] * b[0] + a[5] * b[3] + a[8] * b[6],
        a[2] * b[1] + a[5] * b[4] + a[8] * b[7],
        a[2] * b[2] + a[5] * b[5] + a[8] * b[8],
    )


@njit(cache=True)
def _mmtt(a, b):
    """A @ B^T for row-major 3x3 tuples."""
    return (
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
        a[0] * b[3] + a[1] * b[4] + a[2] * b[5],
        a[0] * b[6] + a[1] * b[7] + a[2] * b[8],
        a[3] * b[0] + a[4] * b[1] + a[5] * b[2],
        a[3] * b[3] + a[4] * b[4] + a[5] * b[5],
        a[3] * b[6] + a[4] * b[7] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[1] + a[8] * b[2],
        a[6] * b[3] + a[7] * b[4] + a[8] * b[5],
        a[6] * b[6] + a[7] * b[7] + a[8] * b[8],
    )


@njit(cache=True)
def _view(viewmats, c):
    """World-to-camera rotation (row-major 9-tuple) and translation of camera c."""
    v = viewmats[c]
    r = (
        np.float64(v[0, 0]), np.float64(v[0, 1]), np.float64(v[0, 2]),
        np.float64(v[1, 0]), np.float64(v[1, 1]), np.float64(v[1, 2]),
        np.float64(v[2, 0]), np.float64(v[2, 1]), np.float64(v[2, 2]),
    )
    t = (np.float64(v[0, 3]), np.float64(v[1, 3]), np.float64(v[2, 3]))
    return r, t


@njit(cache=True)
def _camera_terms(viewmats, Ks, width, height):
    """Per camera, the float64 terms every Gaussian needs, computed once per call: rotation
    (row-major, 0-8), translation (9-11), fx, fy, cx, cy (12-15) and the clamp limits of the
    projection's Jacobian (16-19: +x, -x, +y, -y; gsplat's persp_proj)."""
    n_cam = viewmats.shape[0]
    out = np.empty((n_cam, 20), np.float64)
    for c in range(n_cam):
        rv, tv = _view(viewmats, c)
        for i in range(9):
            out[c, i] = rv[i]
        for i in range(3):
            out[c, 9 + i] = tv[i]
        fx = np.float64(Ks[c, 0, 0])
        fy = np.float64(Ks[c, 1, 1])
        cx = np.float64(Ks[c, 0, 2])
        cy = np.float64(Ks[c, 1, 2])
        out[c, 12] = fx
        out[c, 13] = fy
        out[c, 14] = cx
        out[c, 15] = cy
        tan_fovx = 0.5 * width / fx
        tan_fovy = 0.5 * height / fy
        out[c, 16] = (width - cx) / fx + 0.3 * tan_fovx
        out[c, 17] = cx / fx + 0.3 * tan_fovx
        out[c, 18] = (height - cy) / fy + 0.3 * tan_fovy
        out[c, 19] = cy / fy + 0.3 * tan_fovy
    return out


@njit(cache=True, inline="always")
def _camera_rotation(cams, c):
    return (cams[c, 0], cams[c, 1], cams[c, 2], cams[c, 3], cams[c, 4], cams[c, 5],
            cams[c, 6], cams[c, 7], cams[c, 8])


@njit(cache=True, inline="always")
def _persp_terms(xc, yc, zc, cams, c):
    """Clamped Jacobian terms of the pinhole projection (gsplat's persp_proj) for camera c of
    :func:`_camera_terms`."""
    lim_x_pos = cams[c, 16]
    lim_x_neg = cams[c, 17]
    lim_y_pos = cams[c, 18]
    lim_y_neg = cams[c, 19]
    rz = 1.0 / zc
    rz2 = rz * rz
    u = xc * rz
    v = yc * rz
    tx = zc * min(lim_x_pos, max(-lim_x_neg, u))
    ty = zc * min(lim_y_pos, max(-lim_y_neg, v))
    in_x = u <= lim_x_pos and u >= -lim_x_neg
    in_y = v <= lim_y_pos and v >= -lim_y_neg
    return rz, rz2, tx, ty, in_x, in_y


@njit(cache=True)
def _cov2d(sc, j00, j02, j11, j12):
    """Upper triangle (a, b, c) of J Sigma_c J^T with J = [[j00, 0, j02], [0, j11, j12]]."""
    a = j00 * j00 * sc[0] + 2.0 * j00 * j02 * sc[2] + j02 * j02 * sc[8]
    b = j00 * j11 * sc[1] + j00 * j12 * sc[2] + j02 * j11 * sc[5] + j02 * j12 * sc[8]
    c = j11 * j11 * sc[4] + 2.0 * j11 * j12 * sc[5] + j12 * j12 * sc[8]
    return a, b, c


@njit(cache=True)
def _fits_f32(x):
    return abs(x) < _F32_MAX


# --------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def project_fwd(means, quats, scales, opacities, use_opacity, viewmats, Ks, width, height,
                eps2d, near, far, compensations=None):
    """Project N Gaussians into C cameras.

    Returns radii [C,N,2] int32 (0 = culled), means2d [C,N,2], depths [C,N] and conics
    [C,N,3] (upper triangle of the inverse 2D covariance), float32; culled entries are 0.

    With a ``compensations`` array [C,N] (the 2D mip filter, gsplat's ``antialiased`` mode)
    it receives ``sqrt(max(det(cov2d) / det(cov2d + eps2d I), 0))``, the factor the caller
    multiplies the opacity by, and the opacity-aware box uses the compensated opacity.
    """
    n = means.shape[0]
    n_cam = viewmats.shape[0]
    radii = np.zeros((n_cam, n, 2), np.int32)
    means2d = np.zeros((n_cam, n, 2), np.float32)
    depths = np.zeros((n_cam, n), np.float32)
    conics = np.zeros((n_cam, n, 3), np.float32)
    wf = np.float64(width)
    hf = np.float64(height)
    cams = _camera_terms(viewmats, Ks, wf, hf)
    for g in prange(n):
        cov, _r, _m, _inv, _qn = _covar3d(quats[g], scales[g])
        mx = np.float64(means[g, 0])
        my = np.float64(means[g, 1])
        mz = np.float64(means[g, 2])
        for c in range(n_cam):
            rv = _camera_rotation(cams, c)
            xc = rv[0] * mx + rv[1] * my + rv[2] * mz + cams[c, 9]
            yc = rv[3] * mx + rv[4] * my + rv[5] * mz + cams[c, 10]
            zc = rv[6] * mx + rv[7] * my + rv[8] * mz + cams[c, 11]
            if not (zc >= near and zc <= far) or zc <= 0.0:
                continue
            sc = _mmtt(_mm(rv, cov), rv)
            fx = cams[c, 12]
            fy = cams[c, 13]
            cx = cams[c, 14]
            cy = cams[c, 15]
            rz, rz2, tx, ty, _ix, _iy = _persp_terms(xc, yc, zc, cams, c)
            a, b, cc = _cov2d(sc, fx * rz, -fx * tx * rz2, fy * rz, -fy * ty * rz2)
            det0 = a * cc - b * b
            a += eps2d
            cc += eps2d
            det = a * cc - b * b
            if not (det > 0.0):
                continue
            comp = 1.0
            if compensations is not None:
                comp = math.sqrt(min(max(det0 / det, 0.0), 1.0))
            extend = _FEXTEND
            if use_opacity:
                op = opacities[g] * _F32(comp)
                if not (op >= _FALPHA_THR):
                    continue
                extend = min(extend, math.sqrt(_F32(2.0) * math.log(op / _FALPHA_THR)))
            rx = math.ceil(np.float64(extend) * math.sqrt(a))
            ry = math.ceil(np.float64(extend) * math.sqrt(cc))
            if rx <= 0.0 and ry <= 0.0:
                continue
            u = fx * xc * rz + cx
            v = fy * yc * rz + cy
            if u + rx <= 0.0 or u - rx >= wf or v + ry <= 0.0 or v - ry >= hf:
                continue
            ca = cc / det
            cb = -b / det
            ccc = a / det
            if not (_fits_f32(u) and _fits_f32(v) and _fits_f32(ca) and _fits_f32(cb)
                    and _fits_f32(ccc) and _fits_f32(zc)):
                continue
            radii[c, g, 0] = np.int32(min(rx, RADIUS_MAX))
            radii[c, g, 1] = np.int32(min(ry, RADIUS_MAX))
            means2d[c, g, 0] = u
            means2d[c, g, 1] = v
            depths[c, g] = zc
            conics[c, g, 0] = ca
            conics[c, g, 1] = cb
            conics[c, g, 2] = ccc
            if compensations is not None:
                compensations[c, g] = comp
    return radii, means2d, depths, conics


@njit(parallel=True, cache=True)
def project_bwd(means, quats, scales, viewmats, Ks, width, height, eps2d, radii,
                v_means2d, v_depths, v_conics, v_compensations=None):
    """Vector-Jacobian product of :func:`project_fwd` for means, quats and scales (and, given
    ``v_compensations`` [C,N], through the 2D mip filter's opacity compensation)."""
    n = means.shape[0]
    n_cam = viewmats.shape[0]
    v_means = np.zeros((n, 3), np.float32)
    v_quats = np.zeros((n, 4), np.float32)
    v_scales = np.zeros((n, 3), np.float32)
    wf = np.float64(width)
    hf = np.float64(height)
    cams = _camera_terms(viewmats, Ks, wf, hf)
    for g in prange(n):
        cov, rq, m, inv_norm, qn = _covar3d(quats[g], scales[g])
        mx = np.float64(means[g, 0])
        my = np.float64(means[g, 1])
        mz = np.float64(means[g, 2])
        vm0 = 0.0
        vm1 = 0.0
        vm2 = 0.0
        vs = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        any_cam = False
        for c in range(n_cam):
            if radii[c, g, 0] <= 0 or radii[c, g, 1] <= 0:
                continue
            any_cam = True
            rv = _camera_rotation(cams, c)
            xc = rv[0] * mx + rv[1] * my + rv[2] * mz + cams[c, 9]
            yc = rv[3] * mx + rv[4] * my + rv[5] * mz + cams[c, 10]
            zc = rv[6] * mx + rv[7] * my + rv[8] * mz + cams[c, 11]
            sc = _mmtt(_mm(rv, cov), rv)
            fx = cams[c, 12]
            fy = cams[c, 13]
            rz, rz2, tx, ty, in_x, in_y = _persp_terms(xc, yc, zc, cams, c)
            j00 = fx * rz
            j02 = -fx * tx * rz2
            j11 = fy * rz
            j12 = -fy * ty * rz2
            a, b, cc = _cov2d(sc, j00, j02, j11, j12)
            det0 = a * cc - b * b
            a += eps2d
            cc += eps2d
            det = a * cc - b * b
            # compensation k = sqrt(r), r = det0 / det (clamped to [0, 1]): dk/d(a, b, c)
            ka = 0.0
            kb = 0.0
            kc = 0.0
            if v_compensations is not None:
                r = det0 / det
                vk = np.float64(v_compensations[c, g])
                if r > 0.0 and r < 1.0 and vk != 0.0:
                    vr = vk * 0.5 / math.sqrt(r)
                    a0 = a - eps2d
                    c0 = cc - eps2d
                    ka = vr * (c0 - r * cc) / det
                    kc = vr * (a0 - r * a) / det
                    kb = vr * (-2.0 * b) * (1.0 - r) / det
            # conic P = inverse(cov2d); v_cov2d = -P vP P with vP symmetric
            p00 = cc / det
            p01 = -b / det
            p11 = a / det
            w00 = np.float64(v_conics[c, g, 0])
            w01 = 0.5 * np.float64(v_conics[c, g, 1])
            w11 = np.float64(v_conics[c, g, 2])
            # T = vP @ P
            t00 = w00 * p00 + w01 * p01
            t01 = w00 * p01 + w01 * p11
            t10 = w01 * p00 + w11 * p01
            t11 = w01 * p01 + w11 * p11
            g00 = -(p00 * t00 + p01 * t10)
            g01 = -(p00 * t01 + p01 * t11)
            g11 = -(p01 * t01 + p11 * t11)
            g00 += ka
            g01 += 0.5 * kb  # b is both off-diagonal entries of the symmetric cov2d
            g11 += kc
            # v_Sigma_c += J^T G J (J rows: [j00, 0, j02], [0, j11, j12])
            s00 = j00 * j00 * g00
            s01 = j00 * j11 * g01
            s02 = j00 * (g00 * j02 + g01 * j12)
            s11 = j11 * j11 * g11
            s12 = j11 * (g01 * j02 + g11 * j12)
            s22 = j02 * (g00 * j02 + g01 * j12) + j12 * (g01 * j02 + g11 * j12)
            vsc = (s00, s01, s02, s01, s11, s12, s02, s12, s22)
            # v_mean_c from the mean projection
            vu = np.float64(v_means2d[c, g, 0])
            vv = np.float64(v_means2d[c, g, 1])
            vx = fx * rz * vu
            vy = fy * rz * vv
            vz = -(fx * xc * vu + fy * yc * vv) * rz2
            # v_J = 2 G J Sigma_c  (G, Sigma_c symmetric); J rows r0 = (j00, 0, j02), r1 = (0, j11, j12)
            # (G J) rows: q0 = g00*r0 + g01*r1, q1 = g01*r0 + g11*r1
            q00 = g00 * j00
            q01 = g01 * j11
            q02 = g00 * j02 + g01 * j12
            q10 = g01 * j00
            q11 = g11 * j11
            q12 = g01 * j02 + g11 * j12
            vj00 = 2.0 * (q00 * sc[0] + q01 * sc[3] + q02 * sc[6])
            vj02 = 2.0 * (q00 * sc[2] + q01 * sc[5] + q02 * sc[8])
            vj11 = 2.0 * (q10 * sc[1] + q11 * sc[4] + q12 * sc[7])
            vj12 = 2.0 * (q10 * sc[2] + q11 * sc[5] + q12 * sc[8])
            rz3 = rz2 * rz
            if in_x:
                vx += -fx * rz2 * vj02
            else:
                vz += -fx * rz3 * vj02 * tx
            if in_y:
                vy += -fy * rz2 * vj12
            else:
                vz += -fy * rz3 * vj12 * ty
            vz += (-fx * rz2 * vj00 - fy * rz2 * vj11
                   + 2.0 * fx * tx * rz3 * vj02 + 2.0 * fy * ty * rz3 * vj12)
            vz += np.float64(v_depths[c, g])
            # back to world: v_mean += R^T v_mean_c ; v_Sigma += R^T v_Sigma_c R
            vm0 += rv[0] * vx + rv[3] * vy + rv[6] * vz
            vm1 += rv[1] * vx + rv[4] * vy + rv[7] * vz
            vm2 += rv[2] * vx + rv[5] * vy + rv[8] * vz
            vw = _mm(_mtm(rv, vsc), rv)
            vs = (vs[0] + vw[0], vs[1] + vw[1], vs[2] + vw[2], vs[3] + vw[3], vs[4] + vw[4],
                  vs[5] + vw[5], vs[6] + vw[6], vs[7] + vw[7], vs[8] + vw[8])
        if not any_cam:
            continue
        v_means[g, 0] = vm0
        v_means[g, 1] = vm1
        v_means[g, 2] = vm2
        # Sigma = M M^T: v_M = (vS + vS^T) M ; M = R diag(s)
        vsym = (vs[0] + vs[0], vs[1] + vs[3], vs[2] + vs[6],
                vs[3] + vs[1], vs[4] + vs[4], vs[5] + vs[7],
                vs[6] + vs[2], vs[7] + vs[5], vs[8] + vs[8])
        vmm = _mm(vsym, m)
        s0 = np.float64(scales[g, 0])
        s1 = np.float64(scales[g, 1])
        s2 = np.float64(scales[g, 2])
        v_scales[g, 0] = rq[0] * vmm[0] + rq[3] * vmm[3] + rq[6] * vmm[6]
        v_scales[g, 1] = rq[1] * vmm[1] + rq[4] * vmm[4] + rq[7] * vmm[7]
        v_scales[g, 2] = rq[2] * vmm[2] + rq[5] * vmm[5] + rq[8] * vmm[8]
        if inv_norm == 0.0:
            continue  # identity rule: zero / denormal quaternion gets no gradient
        gr = (vmm[0] * s0, vmm[1] * s1, vmm[2] * s2,
              vmm[3] * s0, vmm[4] * s1, vmm[5] * s2,
              vmm[6] * s0, vmm[7] * s1, vmm[8] * s2)
        w, x, y, z = qn
        # dL/d(normalised q) for R(q) (row-major G = dL/dR)
        dw = 2.0 * (x * (gr[7] - gr[5]) + y * (gr[2] - gr[6]) + z * (gr[3] - gr[1]))
        dx = 2.0 * (-2.0 * x * (gr[4] + gr[8]) + y * (gr[1] + gr[3]) + z * (gr[2] + gr[6])
                    + w * (gr[7] - gr[5]))
        dy = 2.0 * (x * (gr[1] + gr[3]) - 2.0 * y * (gr[0] + gr[8]) + z * (gr[5] + gr[7])
                    + w * (gr[2] - gr[6]))
        dz = 2.0 * (x * (gr[2] + gr[6]) + y * (gr[5] + gr[7]) - 2.0 * z * (gr[0] + gr[4])
                    + w * (gr[3] - gr[1]))
        dot = dw * w + dx * x + dy * y + dz * z
        v_quats[g, 0] = (dw - dot * w) * inv_norm
        v_quats[g, 1] = (dx - dot * x) * inv_norm
        v_quats[g, 2] = (dy - dot * y) * inv_norm
        v_quats[g, 3] = (dz - dot * z) * inv_norm
    return v_means, v_quats, v_scales


# --------------------------------------------------------------------------------------
# Spherical harmonics (degree <= 3, gsplat / Sloan's basis order and signs)
# --------------------------------------------------------------------------------------


@njit(cache=True)
def _sh_basis(degree, x, y, z, b):
    """Write the 16 SH basis values at unit direction (x, y, z) into b (0 above the degree)."""
    b[:] = 0.0
    b[0] = _SH_C0
    if degree >= 1:
        b[1] = -_SH_C1 * y
        b[2] = _SH_C1 * z
        b[3] = -_SH_C1 * x
    if degree >= 2:
        z2 = z * z
        tb = -1.092548430592079 * z
        c1 = x * x - y * y
        s1 = 2.0 * x * y
        b[4] = 0.5462742152960395 * s1
        b[5] = tb * y
        b[6] = 0.9461746957575601 * z2 - 0.3153915652525201
        b[7] = tb * x
        b[8] = 0.5462742152960395 * c1
        if degree >= 3:
            tc = -2.285228997322329 * z2 + 0.4570457994644658
            tb3 = 1.445305721320277 * z
            c2 = x * c1 - y * s1
            s2 = x * s1 + y * c1
            b[9] = -0.5900435899266435 * s2
            b[10] = tb3 * s1
            b[11] = tc * y
            b[12] = z * (1.865881662950577 * z2 - 1.119528997770346)
            b[13] = tc * x
            b[14] = tb3 * c1
            b[15] = -0.5900435899266435 * c2


@njit(cache=True, inline="always")
def _sh_dir_grad(degree, x, y, z, w):
    """d/d(x, y, z) of sum_k w[k] * basis_k(x, y, z) (w[0] unused): the basis derivatives of
    :func:`_sh_basis` written out per degree, so no per-Gaussian arrays are zeroed or looped."""
    gx = -_SH_C1 * w[3]
    gy = -_SH_C1 * w[1]
    gz = _SH_C1 * w[2]
    if degree >= 2:
        k4 = 0.5462742152960395
        kb = -1.092548430592079
        gx += 2.0 * k4 * (y * w[4] + x * w[8]) + kb * z * w[7]
        gy += 2.0 * k4 * (x * w[4] - y * w[8]) + kb * z * w[5]
        gz += kb * (y * w[5] + x * w[7]) + 2.0 * 0.9461746957575601 * z * w[6]
        if degree >= 3:
            z2 = z * z
            c1 = x * x - y * y
            s1 = 2.0 * x * y
            k9 = -0.5900435899266435
            kt = 1.445305721320277
            tc = -2.285228997322329 * z2 + 0.4570457994644658
            dtc = -2.0 * 2.285228997322329 * z
            # s2 = x*s1 + y*c1: ds2/dx = 6xy, ds2/dy = 3(x^2 - y^2); c2 = x*c1 - y*s1:
            # dc2/dx = 3(x^2 - y^2), dc2/dy = -6xy
            gx += (k9 * 6.0 * x * y * w[9] + kt * z * 2.0 * y * w[10] + tc * w[13]
                   + kt * z * 2.0 * x * w[14] + k9 * 3.0 * c1 * w[15])
            gy += (k9 * 3.0 * c1 * w[9] + kt * z * 2.0 * x * w[10] + tc * w[11]
                   - kt * z * 2.0 * y * w[14] - k9 * 6.0 * x * y * w[15])
            gz += (kt * s1 * w[10] + dtc * y * w[11]
                   + (3.0 * 1.865881662950577 * z2 - 1.119528997770346) * w[12]
                   + dtc * x * w[13] + kt * c1 * w[14])
    return gx, gy, gz


@njit(cache=True)
def _unit_dir(means, campos, g, c):
    dx = np.float64(means[g, 0]) - np.float64(campos[c, 0])
    dy = np.float64(means[g, 1]) - np.float64(campos[c, 1])
    dz = np.float64(means[g, 2]) - np.float64(campos[c, 2])
    n2 = dx * dx + dy * dy + dz * dz
    inorm = 1.0 / math.sqrt(n2) if n2 > 0.0 else 0.0
    return dx * inorm, dy * inorm, dz * inorm, inorm


@njit(parallel=True, cache=True)
def sh_fwd(degree, means, campos, coeffs, radii):
    """Evaluate SH colours [C,N,3] (before gsplat's +0.5 shift); culled entries are 0.

    ``coeffs`` is [Cc, N, K, 3] with Cc = 1 (shared) or C (per camera).
    """
    n = means.shape[0]
    n_cam = campos.shape[0]
    per_cam = coeffs.shape[0] > 1
    n_basis = (degree + 1) * (degree + 1)
    colors = np.zeros((n_cam, n, 3), np.float32)
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    for blk in prange(n_blocks):
        b = np.empty(16, np.float64)
        for g in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            for c in range(n_cam):
                if radii[c, g, 0] <= 0 or radii[c, g, 1] <= 0:
                    continue
                x, y, z, _inorm = _unit_dir(means, campos, g, c)
                _sh_basis(degree, x, y, z, b)
                cc = c if per_cam else 0
                for ch in range(3):
                    acc = 0.0
                    for k in range(n_basis):
                        acc += b[k] * np.float64(coeffs[cc, g, k, ch])
                    colors[c, g, ch] = acc
    return colors


@njit(parallel=True, cache=True)
def sh_bwd(degree, means, campos, coeffs, radii, v_colors):
    """VJP of :func:`sh_fwd`: gradients for the coefficients and (via the view direction)
    the means.  With one camera and shared coefficients (training) every Gaussian's gradient
    is written once, so the outputs are not zero-filled first."""
    n = means.shape[0]
    n_cam = campos.shape[0]
    per_cam = coeffs.shape[0] > 1
    n_basis = (degree + 1) * (degree + 1)
    n_k = coeffs.shape[2]
    once = n_cam == 1
    v_coeffs = np.empty(coeffs.shape, np.float32) if once else np.zeros(coeffs.shape, np.float32)
    v_means = np.empty((n, 3), np.float32) if once else np.zeros((n, 3), np.float32)
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    for blk in prange(n_blocks):
        b = np.empty(16, np.float64)
        w = np.empty(16, np.float64)
        for gc in range(blk * _BLOCK * n_cam, min(n, (blk + 1) * _BLOCK) * n_cam):
            g = gc // n_cam
            c = gc - g * n_cam
            cc = c if per_cam else 0
            vc0 = np.float64(v_colors[c, g, 0])
            vc1 = np.float64(v_colors[c, g, 1])
            vc2 = np.float64(v_colors[c, g, 2])
            skip = radii[c, g, 0] <= 0 or radii[c, g, 1] <= 0 or (vc0 == 0.0 and vc1 == 0.0 and vc2 == 0.0)
            if skip:
                if once:
                    v_coeffs[cc, g, :, :] = 0.0
                    v_means[g, :] = 0.0
                continue
            x, y, z, inorm = _unit_dir(means, campos, g, c)
            _sh_basis(degree, x, y, z, b)
            if once:
                for k in range(n_basis):
                    v_coeffs[cc, g, k, 0] = b[k] * vc0
                    v_coeffs[cc, g, k, 1] = b[k] * vc1
                    v_coeffs[cc, g, k, 2] = b[k] * vc2
                for k in range(n_basis, n_k):
                    v_coeffs[cc, g, k, 0] = 0.0
                    v_coeffs[cc, g, k, 1] = 0.0
                    v_coeffs[cc, g, k, 2] = 0.0
            else:
                for k in range(n_basis):
                    v_coeffs[cc, g, k, 0] += b[k] * vc0
                    v_coeffs[cc, g, k, 1] += b[k] * vc1
                    v_coeffs[cc, g, k, 2] += b[k] * vc2
            if degree == 0 or inorm == 0.0:
                if once:
                    v_means[g, :] = 0.0
                continue
            w[:] = 0.0
            for k in range(1, n_basis):
                w[k] = (vc0 * np.float64(coeffs[cc, g, k, 0]) + vc1 * np.float64(coeffs[cc, g, k, 1])
                        + vc2 * np.float64(coeffs[cc, g, k, 2]))
            gx, gy, gz = _sh_dir_grad(degree, x, y, z, w)
            dot = gx * x + gy * y + gz * z
            if once:
                v_means[g, 0] = (gx - dot * x) * inorm
                v_means[g, 1] = (gy - dot * y) * inorm
                v_means[g, 2] = (gz - dot * z) * inorm
            else:
                v_means[g, 0] += (gx - dot * x) * inorm
                v_means[g, 1] += (gy - dot * y) * inorm
                v_means[g, 2] += (gz - dot * z) * inorm
    return v_coeffs, v_means


# --------------------------------------------------------------------------------------
# Tile binning and load balancing
# --------------------------------------------------------------------------------------


@njit(cache=True)
def _tile_rect(u, v, rx, ry, tile_w, tile_h):
    """Tiles [x0, x1) x [y0, y1) touched by a Gaussian's bounding box (gsplat's rule)."""
    tx = u / _TS
    ty = v / _TS
    trx = rx / _TS
    try_ = ry / _TS
    x0 = min(max(0.0, math.floor(tx - trx)), np.float64(tile_w))
    y0 = min(max(0.0, math.floor(ty - try_)), np.float64(tile_h))
    x1 = min(max(0.0, math.ceil(tx + trx)), np.float64(tile_w))
    y1 = min(max(0.0, math.ceil(ty + try_)), np.float64(tile_h))
    return np.int64(x0), np.int64(y0), np.int64(x1), np.int64(y1)


@njit(cache=True)
def _argsort_depths(depths):
    """Stable argsort of positive float32 depths: LSD radix sort (3 x 11 bits) on the bit
    patterns, which order like the values for non-negative floats."""
    n = depths.shape[0]
    keys = depths.view(np.uint32)
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    for shift in (0, 11, 22):
        count = np.zeros(2049, np.int64)
        for i in range(n):
            count[((keys[idx[i]] >> np.uint32(shift)) & np.uint32(2047)) + 1] += 1
        for b in range(2048):
            count[b + 1] += count[b]
        for i in range(n):
            j = idx[i]
            d = (keys[j] >> np.uint32(shift)) & np.uint32(2047)
            tmp[count[d]] = j
            count[d] += 1
        idx, tmp = tmp, idx
    return idx


@njit(cache=True)
def tile_order(costs):
    """Tiles sorted by decreasing cost estimate: workers take them in this order from a
    shared atomic counter, so long tiles start first and no worker idles while another
    (e.g. preempted on a busy machine) still holds a queue."""
    return np.argsort(-costs, kind="mergesort")


@njit(cache=True)
def forward_costs(tile_offsets):
    """Cost estimate per tile for the forward pass: its intersection count (+ overhead)."""
    n_tiles = tile_offsets.shape[0] - 1
    costs = np.empty(n_tiles, np.int64)
    for t in range(n_tiles):
        costs[t] = tile_offsets[t + 1] - tile_offsets[t] + 8
    return costs


# --------------------------------------------------------------------------------------
# Compositing
# --------------------------------------------------------------------------------------
# Everything a tile needs about one (camera, Gaussian) is packed into one 64-byte float32
# record, so each visit of a Gaussian costs one cache line instead of five.
_R_MX, _R_MY, _R_CA, _R_CB, _R_CC, _R_OP = 0, 1, 2, 3, 4, 5  # mean, conic, opacity
_R_C0, _R_C1, _R_C2, _R_C3 = 6, 7, 8, 9  # colour (RGB + depth)
_R_SCAP = 10  # smax + 1, see prepare_splats
_R_RY, _R_RX, _R_PAD, _R_SLOPE, _R_SMAX = 11, 12, 13, 14, 15  # footprint; RY < 0: unbounded
_N_REC = 16


@njit(parallel=True, cache=True)
def prepare_splats(means2d, conics, rgb, depths, opacities):
    """Pack the per-(camera, Gaussian) inputs of compositing into [CN, 16] records.

    ``means2d`` [C,N,2], ``conics`` [C,N,3], ``depths`` [C,N], ``opacities`` [N] or [C,N]
    (per camera, as the 2D mip filter's compensation makes them) and ``rgb`` [C,N,3] or
    [1,N,3] (one colour per Gaussian for all cameras).

    Footprint: alpha >= 1/255 needs sigma <= smax = log(255 * opacity), an ellipse with
    half-extents rx, ry (computed in float64).  ``pad`` (px) absorbs float32 rounding of
    the per-pixel test and of these bounds (far below 0.1 px except for large coordinates
    or huge footprints, covered by the relative terms).  A numerically indefinite conic is
    marked unbounded (ry = -1): whole tiles are then tested.  Lanes clamp sigma at
    ``smax + 1``, where no pixel can pass, to keep exp() away from slow denormals without
    changing any decision.
    """
    n_cam = means2d.shape[0]
    n = means2d.shape[1]
    shared = rgb.shape[0] == 1
    rec = np.zeros((n_cam * n, _N_REC), np.float32)
    op_flat = opacities.reshape(opacities.size)
    per_camera = op_flat.shape[0] != n
    for i in prange(n_cam * n):
        c = i // n
        g = i - c * n
        op = op_flat[i] if per_camera else op_flat[g]
        rec[i, _R_MX] = means2d[c, g, 0]
        rec[i, _R_MY] = means2d[c, g, 1]
        rec[i, _R_CA] = conics[c, g, 0]
        rec[i, _R_CB] = conics[c, g, 1]
        rec[i, _R_CC] = conics[c, g, 2]
        rec[i, _R_OP] = op
        cc_ = 0 if shared else c
        rec[i, _R_C0] = rgb[cc_, g, 0]
        rec[i, _R_C1] = rgb[cc_, g, 1]
        rec[i, _R_C2] = rgb[cc_, g, 2]
        rec[i, _R_C3] = depths[c, g]
        rec[i, _R_RY] = -1.0
        if not (op >= _FALPHA_THR):
            continue  # never passes the threshold; tiles skip it
        mx = np.float64(means2d[c, g, 0])
        my = np.float64(means2d[c, g, 1])
        ca = np.float64(conics[c, g, 0])
        cb = np.float64(conics[c, g, 1])
        cc = np.float64(conics[c, g, 2])
        smax = math.log(np.float64(op) / np.float64(ALPHA_THRESHOLD))
        det = ca * cc - cb * cb
        rec[i, _R_SCAP] = smax + 1.0
        pad = 0.1 + 1e-6 * (abs(mx) + abs(my))
        if det > 0.0 and ca > 0.0 and cc > 0.0:
            ry = math.sqrt(max(2.0 * smax * ca / det, 0.0))
            rx = math.sqrt(max(2.0 * smax * cc / det, 0.0))
            rec[i, _R_RY] = ry
            rec[i, _R_RX] = rx
            rec[i, _R_PAD] = pad + 1e-5 * (rx + ry)
            rec[i, _R_SLOPE] = cb / ca
            # widened by the float32 rounding of the stored terms
            rec[i, _R_SMAX] = smax * (1.0 + 1e-5) + 1e-6
        else:
            rec[i, _R_PAD] = pad
    return rec


@njit(cache=True)
def _tile_box(tile, tile_w, tile_h, width, height):
    """Camera index and pixel box [x0, x1) x [y0, y1) of a flat tile index."""
    per_img = tile_w * tile_h
    c = tile // per_img
    t = tile - c * per_img
    ty = t // tile_w
    tx = t - ty * tile_w
    x0 = tx * _TS
    y0 = ty * _TS
    x1 = min(x0 + _TS, width)
    y1 = min(y0 + _TS, height)
    return c, x0, y0, x1, y1


@njit(cache=True)
def _visit(rec, g, x0, y0, x1, y1):
    """Rows [ylo, yhi] of tile (x0, y0, x1, y1) that a Gaussian's footprint can reach (an
    empty range if its columns miss the tile), and whether each row needs its own column
    test (the footprint crosses the tile's left or right edge)."""
    ry = np.float64(rec[g, _R_RY])
    if ry < 0.0:
        return np.int64(y0), np.int64(y1 - 1), False
    mx = np.float64(rec[g, _R_MX])
    my = np.float64(rec[g, _R_MY])
    rx = np.float64(rec[g, _R_RX])
    pad = np.float64(rec[g, _R_PAD])
    ylo = max(math.floor(my - ry - 0.5 - pad), np.float64(y0))
    yhi = min(math.ceil(my + ry - 0.5 + pad), np.float64(y1 - 1))
    if mx + rx + pad < x0 + 0.5 or mx - rx - pad > x1 - 0.5:
        yhi = ylo - 1.0
    row_test = mx - rx - pad < x0 + 0.5 or mx + rx + pad > x1 - 0.5
    return np.int64(ylo), np.int64(yhi), row_test


@njit(cache=True, inline="always")
def _row_misses_tile(mx, dy, pad, slope, ca, cb, cc, smax, x0, x1):
    """True when no pixel centre of a tile row can pass the alpha threshold (float64).

    Along the row (dy = my - py fixed) sigma is a parabola in dx = mx - px, minimal at
    dx = -(cb / ca) dy; the row misses when its minimum over the tile's (padded) columns
    exceeds smax.  No sqrt or division, so all rows of a tile are tested in one vector loop.
    """
    dx = -slope * dy
    dx = min(max(dx, mx - (x1 - 0.5) - pad), mx - (x0 + 0.5) + pad)
    q = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    return q > smax


@njit(cache=True)
def _tile_rows(rec, g, x0, y0, x1, y1):
    """Rows [ylo, yhi] of tile (x0, y0, x1, y1) that record g's {alpha >= 1/255} footprint
    can reach; yhi < ylo when it misses the tile.

    The bounding rows and columns of the ellipse come first; when the ellipse crosses the
    tile's left or right edge, each row is also tested against the tile's columns
    (:func:`_row_misses_tile`) and the range is cut to the first and last row that passes.
    The footprint is convex, so no row in between can miss; were float rounding ever to
    make one, compositing it changes nothing (the per-pixel test decides).  Rows outside
    the image of a border tile are never in the range.
    """
    if not (rec[g, _R_OP] >= _FALPHA_THR):
        return np.int64(y0), np.int64(y0 - 1)  # alpha <= opacity never reaches 1/255
    ylo, yhi, row_test = _visit(rec, g, x0, y0, x1, y1)
    if not row_test or yhi < ylo:
        return ylo, yhi
    my = rec[g, _R_MY]
    mx = np.float64(rec[g, _R_MX])
    pad = np.float64(rec[g, _R_PAD])
    slope = np.float64(rec[g, _R_SLOPE])
    ca = np.float64(rec[g, _R_CA])
    cb = np.float64(rec[g, _R_CB])
    cc = np.float64(rec[g, _R_CC])
    smax = np.float64(rec[g, _R_SMAX])
    first = np.int64(_TS)
    last = np.int64(-1)
    for r in range(_TS):  # fixed length and branch-free: LLVM vectorises it
        y = y0 + r
        dy = np.float64(my - (_F32(y) + _F05))  # the float32 dy of the pixel loops
        hit = (y >= ylo) & (y <= yhi) & ~_row_misses_tile(mx, dy, pad, slope, ca, cb, cc,
                                                           smax, x0, x1)
        first = min(first, r if hit else _TS)
        last = max(last, r if hit else -1)
    if last < 0:
        return np.int64(y0), np.int64(y0 - 1)
    return np.int64(y0 + first), np.int64(y0 + last)


@njit(parallel=True, cache=True)
def _splat_tiles(rec, radii, tile_w, tile_h, width, height):
    """The tiles each (camera, Gaussian) cg reaches, out of its bounding box of tiles
    (gsplat's rule): ``n_hit[cg + 1]`` of them, listed from ``box_offsets[cg]`` in
    row-major tile order as the flat tile index ``hit_tiles`` (camera included) and the
    packed reachable rows ``hit_rows`` (``ylo | yhi << 8``, relative to the tile)."""
    n_cam = radii.shape[0]
    n = radii.shape[1]
    rects = np.zeros((n_cam * n, 4), np.int64)
    area = np.zeros(n_cam * n + 1, np.int64)
    for cg in prange(n_cam * n):
        c = cg // n
        g = cg - c * n
        if radii[c, g, 0] <= 0 or radii[c, g, 1] <= 0:
            continue
        x0, y0, x1, y1 = _tile_rect(np.float64(rec[cg, _R_MX]), np.float64(rec[cg, _R_MY]),
                                    np.float64(radii[c, g, 0]), np.float64(radii[c, g, 1]),
                                    tile_w, tile_h)
        rects[cg, 0] = x0
        rects[cg, 1] = y0
        rects[cg, 2] = x1
        rects[cg, 3] = y1
        area[cg + 1] = (x1 - x0) * (y1 - y0)
    box_offsets = np.cumsum(area)
    hit_tiles = np.empty(box_offsets[-1], np.int32)
    hit_rows = np.empty(box_offsets[-1], np.int32)
    n_hit = np.zeros(n_cam * n + 1, np.int64)
    per_img = tile_w * tile_h
    for cg in prange(n_cam * n):
        j = box_offsets[cg]
        base = (cg // n) * per_img
        for ty in range(rects[cg, 1], rects[cg, 3]):
            py0 = ty * _TS
            py1 = min(py0 + _TS, height)
            for tx in range(rects[cg, 0], rects[cg, 2]):
                px0 = tx * _TS
                ylo, yhi = _tile_rows(rec, cg, px0, py0, min(px0 + _TS, width), py1)
                if yhi >= ylo:
                    hit_tiles[j] = np.int32(base + ty * tile_w + tx)
                    hit_rows[j] = np.int32((ylo - py0) | ((yhi - py0) << 8))
                    j += 1
        n_hit[cg + 1] = j - box_offsets[cg]
    return box_offsets, hit_tiles, hit_rows, n_hit


@njit(cache=True)
def _depth_order(n_hit, depths):
    """Records (``c * N + g``) that reach at least one tile, sorted by camera and then by
    depth (stable: ties keep index order, like gsplat's radix sort)."""
    n_cam = depths.shape[0]
    n = depths.shape[1]
    out = np.empty(np.count_nonzero(n_hit[1:]), np.int64)
    i = 0
    for c in range(n_cam):
        vis = np.flatnonzero(n_hit[c * n + 1:(c + 1) * n + 1])
        order = _argsort_depths(depths[c][vis])
        out[i:i + vis.shape[0]] = c * n + vis[order]
        i += vis.shape[0]
    return out


@njit(parallel=True, cache=True)
def bin_splats(rec, radii, depths, tile_w, tile_h, width, height, n_workers):
    """Sort the (camera, Gaussian)-tile intersections by (camera, tile, depth).

    Candidates are the tiles of each Gaussian's bounding box (gsplat's rule); those its
    {alpha >= 1/255} footprint cannot reach are dropped (a fifth on the benchmark scene).
    Returns ``tile_offsets`` [C*tile_h*tile_w + 1] (int64), ``flatten_ids`` [n_isects]
    (int32 record index ``c * N + g``) and ``isect_rows`` [n_isects] (int32, rows
    ``ylo | yhi << 8`` of the tile to composite): tile t's Gaussians, front to back, are
    ``flatten_ids[tile_offsets[t]:tile_offsets[t + 1]]``.  Ties in depth keep index order
    (a stable sort, like gsplat's radix sort).  Also returns the Gaussian-major view
    ``gauss_offsets`` [C*N + 1], ``isect_of`` [n_isects]: the intersections of record cg
    (in tile order) are ``isect_of[gauss_offsets[cg]:gauss_offsets[cg + 1]]``.

    ``n_workers`` contiguous chunks of the depth order are scattered in parallel, each
    into its own slots of every tile (chunk w's entries follow chunk w-1's), so the
    result does not depend on the number of workers.
    """
    n_tiles = radii.shape[0] * tile_w * tile_h
    box_offsets, hit_tiles, hit_rows, n_hit = _splat_tiles(rec, radii, tile_w, tile_h, width,
                                                           height)
    order = _depth_order(n_hit, depths)
    n_rec = order.shape[0]
    chunk_counts = np.zeros((n_workers, n_tiles), np.int64)
    for w in prange(n_workers):
        for oi in range(w * n_rec // n_workers, (w + 1) * n_rec // n_workers):
            cg = order[oi]
            for j in range(box_offsets[cg], box_offsets[cg] + n_hit[cg + 1]):
                chunk_counts[w, hit_tiles[j]] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    cursors = np.empty((n_workers, n_tiles), np.int64)
    for t in range(n_tiles):
        at = offsets[t]
        for w in range(n_workers):
            cursors[w, t] = at
            at += chunk_counts[w, t]
        offsets[t + 1] = at
    n_isects = offsets[-1]
    flatten_ids = np.empty(n_isects, np.int32)
    isect_rows = np.empty(n_isects, np.int32)
    gauss_offsets = np.cumsum(n_hit)
    isect_of = np.empty(n_isects, np.int64)
    for w in prange(n_workers):
        cursor = cursors[w]
        for oi in range(w * n_rec // n_workers, (w + 1) * n_rec // n_workers):
            cg = order[oi]
            jg = gauss_offsets[cg]
            for j in range(box_offsets[cg], box_offsets[cg] + n_hit[cg + 1]):
                t = hit_tiles[j]
                slot = cursor[t]
                flatten_ids[slot] = np.int32(cg)
                isect_rows[slot] = hit_rows[j]
                isect_of[jg] = slot
                cursor[t] = slot + 1
                jg += 1
    return offsets, flatten_ids, isect_rows, gauss_offsets, isect_of


# Forward per-pixel state: one flat float32 array with compile-time field offsets (see the
# backward state below for why); the last contributor's index is kept as int32 bits.
_F_T = np.uint64(0 * _TP)  # transmittance; stored negated once the pixel is done
_F_A0 = np.uint64(1 * _TP)  # 4 fields: accumulated colour (RGB + depth)
_F_A1 = np.uint64(2 * _TP)
_F_A2 = np.uint64(3 * _TP)
_F_A3 = np.uint64(4 * _TP)
_F_LAST = np.uint64(5 * _TP)  # int32 bits of the last contributing intersection index
_F_MED = np.uint64(6 * _TP)  # median depth: the depth of the Gaussian that takes T across 0.5 (0: none)
_FWD_FIELDS = 7


@njit(cache=True, error_model="numpy", fastmath=_PIXEL_MATH)
def _fwd_tile(tile, rec, backgrounds, width, height, tile_w, tile_h, tile_offsets, flatten_ids,
              isect_rows, rgb, depth, alpha_img, t_final, acc_depth, last_ids, bwd_costs, st,
              row_done, median):
    """Composite one tile front to back, Gaussian by Gaussian.

    Each reachable row is a fixed 16-lane, branch-free loop that LLVM vectorises, applying
    the per-pixel rules of gsplat's forward kernel: alpha = min(0.999, o exp(-sigma)),
    skip if sigma < 0 or alpha < 1/255, stop (exclusive) when T would drop to <= 1e-4.
    A row whose pixels have all stopped is skipped (``row_done`` counts its stopped lanes,
    those outside the image included): its lanes would change nothing.  The row loop only
    ORs the lanes' stop flags and recounts a row when one stopped: an int64 counter in the
    loop made LLVM use 8-lane vectors instead of 16.

    ``median`` is None or a [C,H,W,1] image for the median depth: the depth of the Gaussian whose
    compositing takes the transmittance from above 0.5 to 0.5 or below (0 where it never does);
    numba prunes its code at compile time when it is None, so training pays nothing for it.
    """
    c, x0, y0, x1, y1 = _tile_box(tile, tile_w, tile_h, width, height)
    none = _int32_bits_as_float32(np.int32(-1))
    for i in range(_TP):
        p = np.uint64(i)
        ly = i // _TS
        lx = i - ly * _TS
        # lanes outside the image start done
        st[p + _F_T] = _F1 if (x0 + lx < x1 and y0 + ly < y1) else -_F1
        st[p + _F_A0] = _F0
        st[p + _F_A1] = _F0
        st[p + _F_A2] = _F0
        st[p + _F_A3] = _F0
        st[p + _F_LAST] = none
        st[p + _F_MED] = _F0
    row_w = x1 - x0
    row_done[:] = _TS - row_w  # stopped lanes per row, counting those outside the image
    n_pix = _TS * (y1 - y0)
    n_done = (_TS - row_w) * (y1 - y0)
    x0c = _F32(x0) + _F05
    for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
        g = flatten_ids[k]
        op = rec[g, _R_OP]
        mx = rec[g, _R_MX]
        my = rec[g, _R_MY]
        ca = rec[g, _R_CA]
        cb = rec[g, _R_CB]
        cc = rec[g, _R_CC]
        c0 = rec[g, _R_C0]
        c1 = rec[g, _R_C1]
        c2 = rec[g, _R_C2]
        c3 = rec[g, _R_C3]
        s_cap = rec[g, _R_SCAP]
        rows = isect_rows[k]
        kbits = _int32_bits_as_float32(np.int32(k))
        for y in range(y0 + (rows & 255), y0 + (rows >> 8) + 1):
            if row_done[y - y0] >= _TS:
                continue  # every pixel of this row has stopped
            dy = my - (_F32(y) + _F05)
            ccdy2 = cc * dy * dy
            any_stop = False
            base = np.uint64((y - y0) * _TS)
            for lx in range(np.uint64(_TS)):
                p = base + lx
                dx = mx - (x0c + _F32(lx))
                sigma = _F05 * (ca * dx * dx + ccdy2) + cb * dx * dy
                alpha = min(_FALPHA_MAX, op * exp_neg(min(max(sigma, _F0), s_cap)))
                t_cur = st[p + _F_T]
                l_cur = st[p + _F_LAST]
                next_t = t_cur * (_F1 - alpha)
                ok = (sigma >= _F0) & (alpha >= _FALPHA_THR) & (t_cur > _F0)
                stop = ok & (next_t <= _FT_MIN)
                use = ok & (next_t > _FT_MIN)
                vis = alpha * t_cur if use else _F0
                st[p + _F_A0] += c0 * vis
                st[p + _F_A1] += c1 * vis
                st[p + _F_A2] += c2 * vis
                st[p + _F_A3] += c3 * vis
                st[p + _F_T] = next_t if use else (-t_cur if stop else t_cur)
                st[p + _F_LAST] = kbits if use else l_cur
                if median is not None:
                    crosses = use & (t_cur > _F05) & (next_t <= _F05)
                    st[p + _F_MED] = c3 if crosses else st[p + _F_MED]
                any_stop |= stop
            if any_stop:  # rare (a pixel stops once): recount the row's stopped lanes
                n_row = 0
                for lx in range(np.uint64(_TS)):
                    n_row += st[base + lx + _F_T] < _F0
                n_done += n_row - row_done[y - y0]
                row_done[y - y0] = n_row
        if n_done >= n_pix:
            break
    max_last = np.int64(-1)
    for y in range(y0, y1):
        for x in range(x0, x1):
            p = np.uint64((y - y0) * _TS + (x - x0))
            t_cur = abs(st[p + _F_T])
            alpha = _F1 - t_cur
            rgb[c, y, x, 0] = st[p + _F_A0] + t_cur * backgrounds[c, 0]
            rgb[c, y, x, 1] = st[p + _F_A1] + t_cur * backgrounds[c, 1]
            rgb[c, y, x, 2] = st[p + _F_A2] + t_cur * backgrounds[c, 2]
            depth[c, y, x, 0] = st[p + _F_A3] / max(alpha, _FDEPTH_EPS)
            alpha_img[c, y, x, 0] = alpha
            t_final[c, y, x] = t_cur
            acc_depth[c, y, x] = st[p + _F_A3]
            lk = _float32_bits_as_int32(st[p + _F_LAST])
            last_ids[c, y, x] = lk
            max_last = max(max_last, np.int64(lk))
            if median is not None:
                median[c, y, x, 0] = st[p + _F_MED]
    # the backward pass walks this tile's intersections up to its last contributor
    bwd_costs[tile] = max(max_last - tile_offsets[tile] + 1, 0) + 8


@njit(parallel=True, cache=True)
def rasterize_fwd(rec, backgrounds, width, height, tile_w, tile_h, tile_offsets, flatten_ids,
                  isect_rows, order, n_workers, median=None):
    """Composite 4 channels (RGB + depth) of records ``rec`` [CN,16] (prepare_splats) over
    ``backgrounds`` [C,3] (depth has none).

    ``n_workers`` workers take tiles in ``order`` (:func:`tile_order`) from a shared
    counter.  Returns RGB [C,H,W,3] (background included), expected depth [C,H,W,1]
    (accumulated depth / max(alpha, DEPTH_ALPHA_EPS)), alpha [C,H,W,1], the final transmittance and
    the accumulated depth [C,H,W] (for the backward pass), the index of the last
    contributing intersection per pixel [C,H,W] int32 (-1 if none) and per-tile cost
    estimates for ordering the backward pass. ``median``: None, or a [C,H,W,1] float32 array
    that receives the median depth (see :func:`_fwd_tile`).
    """
    n_cam = backgrounds.shape[0]
    rgb = np.empty((n_cam, height, width, 3), np.float32)
    depth = np.empty((n_cam, height, width, 1), np.float32)
    alpha_img = np.empty((n_cam, height, width, 1), np.float32)
    t_final = np.empty((n_cam, height, width), np.float32)
    acc_depth = np.empty((n_cam, height, width), np.float32)
    last_ids = np.empty((n_cam, height, width), np.int32)
    bwd_costs = np.empty(tile_offsets.shape[0] - 1, np.int64)
    n_tiles = order.shape[0]
    counter = np.zeros(1, np.int64)
    for _w in prange(n_workers):
        st = np.empty(_FWD_FIELDS * _TP, np.float32)
        row_done = np.empty(_TS, np.int64)
        i = _atomic_fetch_add(counter, 1)
        while i < n_tiles:
            _fwd_tile(order[i], rec, backgrounds, width, height, tile_w, tile_h,
                      tile_offsets, flatten_ids, isect_rows, rgb, depth, alpha_img, t_final,
                      acc_depth, last_ids, bwd_costs, st, row_done, median)
            i = _atomic_fetch_add(counter, 1)
    return rgb, depth, alpha_img, t_final, acc_depth, last_ids, bwd_costs


# Backward per-pixel state lives in one flat float32 array of _BWD_FIELDS x 256 with
# compile-time field offsets (uint64, so no wrap-around code): LLVM then sees constant
# distances between fields and vectorises the row loop without runtime alias checks.
_O_T = np.uint64(0 * _TP)  # transmittance, recovered backwards
_O_W0 = np.uint64(1 * _TP)  # 4 fields: dL/d(output colour)
_O_W1 = np.uint64(2 * _TP)
_O_W2 = np.uint64(3 * _TP)
_O_W3 = np.uint64(4 * _TP)
_O_D = np.uint64(5 * _TP)  # T_final (dL/dalpha_out - bg . w) - (colour behind) . w, see below
_O_LAST = np.uint64(6 * _TP)  # int32 bits of the pixel's last contributing intersection
_BWD_FIELDS = 7
# Per-lane sums of one Gaussian in one tile (16 lanes each), in their own array: in the
# state array LLVM could not prove them apart from the row's fields and would not vectorise.
_L_U = np.uint64(0 * _TS)  # sum of u = dL/dalpha * dalpha/dopacity (the opacity gradient)
_L_QY = np.uint64(1 * _TS)  # sum of u * dy
_L_QYY = np.uint64(2 * _TS)  # sum of u * dy^2
_L_C0 = np.uint64(3 * _TS)  # 4 sums: colour (RGB + depth) gradients
_L_C1 = np.uint64(4 * _TS)
_L_C2 = np.uint64(5 * _TS)
_L_C3 = np.uint64(6 * _TS)
_L_AX = np.uint64(7 * _TS)  # 2 sums of per-pixel |dL/dmeans2d| (absgrad only)
_L_AY = np.uint64(8 * _TS)
_N_LANE_SUMS = 9


@njit(cache=True, error_model="numpy", fastmath=_PIXEL_MATH)
def _bwd_tile(tile, rec, backgrounds, width, height, tile_w, tile_h, tile_offsets, flatten_ids,
              isect_rows, t_final, acc_depth, last_ids, v_rgb, v_depth, v_alpha, isect_grads, st,
              row_last, lanes, with_abs):
    """Backward of one tile by reverse traversal, 16-lane rows like :func:`_fwd_tile`.

    Per-pixel rules follow gsplat's backward kernel: T is recovered by dividing by
    (1 - alpha) and the alpha-cap branch gets no gradient.  Two exact rewrites keep the
    row loop short:

    * the colour accumulated behind the current Gaussian only enters through its dot
      product with the pixel's dL/dcolour ``w``, so one scalar per pixel is tracked,
      ``D = T_final (dL/dalpha_out - bg . w) - (colour behind) . w``, and
      ``dL/dalpha = T (c . w) + D / (1 - alpha)``;
    * with ``u = dL/dalpha * exp(-sigma)`` (the opacity gradient) every screen-space
      gradient is ``-opacity * u`` times a polynomial in (dx, dy); dy is fixed along a row
      and dx along a lane, so the lanes sum u, u dy and u dy^2 over rows and the dx
      factors are applied once per Gaussian and tile, before the 16 lanes are folded.

    Every intersection k of the tile gets a row in ``isect_grads`` (zero if it contributes
    nothing).  ``error_model="numpy"`` drops numba's zero-division check (1 - alpha >=
    0.001 here), which would block vectorisation.  ``with_abs`` is None or an (unused)
    array: numba prunes the absolute-gradient sums at compile time when it is None.  A row
    is skipped for intersections behind all of its pixels' last contributors
    (``row_last``): its lanes would add nothing.
    """
    c, x0, y0, x1, y1 = _tile_box(tile, tile_w, tile_h, width, height)
    max_last = np.int32(-1)
    row_last[:] = -1
    for i in range(_TP):
        p = np.uint64(i)
        ly = i // _TS
        lx = i - ly * _TS
        y = y0 + ly
        x = x0 + lx
        if y < y1 and x < x1:
            t_f = t_final[c, y, x]
            w0 = v_rgb[c, y, x, 0]
            w1 = v_rgb[c, y, x, 1]
            w2 = v_rgb[c, y, x, 2]
            # expected depth = accumulated depth / max(alpha, eps): chain rule as autograd's
            alpha = _F1 - t_f
            den = max(alpha, _FDEPTH_EPS)
            v_d = v_depth[c, y, x, 0]
            w3 = v_d / den
            v_al = v_alpha[c, y, x, 0]
            if alpha >= _FDEPTH_EPS:
                v_al -= v_d * ((acc_depth[c, y, x] / den) / den)
            bg_dot = backgrounds[c, 0] * w0 + backgrounds[c, 1] * w1 + backgrounds[c, 2] * w2
            st[p + _O_T] = t_f
            st[p + _O_W0] = w0
            st[p + _O_W1] = w1
            st[p + _O_W2] = w2
            st[p + _O_W3] = w3
            st[p + _O_D] = t_f * (v_al - bg_dot)
            lk = last_ids[c, y, x]
            st[p + _O_LAST] = _int32_bits_as_float32(lk)
            max_last = max(max_last, lk)
            row_last[ly] = max(row_last[ly], lk)
        else:  # lanes outside the image never match (last = -1) and contribute nothing
            st[p + _O_T] = _F1
            st[p + _O_W0] = _F0
            st[p + _O_W1] = _F0
            st[p + _O_W2] = _F0
            st[p + _O_W3] = _F0
            st[p + _O_D] = _F0
            st[p + _O_LAST] = _int32_bits_as_float32(np.int32(-1))
    x0c = _F32(x0) + _F05
    start = tile_offsets[tile]
    end = tile_offsets[tile + 1]
    stop = min(end - 1, np.int64(max_last))  # max_last is -1 or an index in [start, end)
    for k in range(max(stop + 1, start), end):
        isect_grads[k, :] = _F0  # behind every pixel's last contributor
    for k in range(stop, start - 1, -1):
        g = flatten_ids[k]
        op = rec[g, _R_OP]
        mx = rec[g, _R_MX]
        my = rec[g, _R_MY]
        ca = rec[g, _R_CA]
        cb = rec[g, _R_CB]
        cc = rec[g, _R_CC]
        c0 = rec[g, _R_C0]
        c1 = rec[g, _R_C1]
        c2 = rec[g, _R_C2]
        c3 = rec[g, _R_C3]
        s_cap = rec[g, _R_SCAP]
        rows = isect_rows[k]
        k32 = np.int32(k)
        touched = False
        for y in range(y0 + (rows & 255), y0 + (rows >> 8) + 1):
            if k32 > row_last[y - y0]:
                continue  # behind every pixel's last contributor in this row
            dy = my - (_F32(y) + _F05)
            if not touched:
                for i in range(np.uint64(_N_LANE_SUMS * _TS)):  # constant size: inline stores
                    lanes[i] = _F0
                touched = True
            ccdy2 = cc * dy * dy
            dy2 = dy * dy
            base = np.uint64((y - y0) * _TS)
            for lx in range(np.uint64(_TS)):
                p = base + lx
                dx = mx - (x0c + _F32(lx))
                sigma = _F05 * (ca * dx * dx + ccdy2) + cb * dx * dy
                vis = exp_neg(min(max(sigma, _F0), s_cap))
                alpha = min(_FALPHA_MAX, op * vis)
                ok = (sigma >= _F0) & (alpha >= _FALPHA_THR) & (k32 <= _float32_bits_as_int32(st[p + _O_LAST]))
                ra = _F1 / (_F1 - alpha)
                t_old = st[p + _O_T]
                t_cur = t_old * ra
                w0 = st[p + _O_W0]
                w1 = st[p + _O_W1]
                w2 = st[p + _O_W2]
                w3 = st[p + _O_W3]
                d_cur = st[p + _O_D]
                cw = c0 * w0 + c1 * w1 + c2 * w2 + c3 * w3
                v_al = t_cur * cw + ra * d_cur
                grad_ok = ok & (op * vis <= _FALPHA_MAX)
                u = vis * v_al if grad_ok else _F0
                lanes[lx + _L_U] += u
                lanes[lx + _L_QY] += u * dy
                lanes[lx + _L_QYY] += u * dy2
                fac_ok = alpha * t_cur if ok else _F0
                lanes[lx + _L_C0] += fac_ok * w0
                lanes[lx + _L_C1] += fac_ok * w1
                lanes[lx + _L_C2] += fac_ok * w2
                lanes[lx + _L_C3] += fac_ok * w3
                if with_abs is not None:
                    v_sigma = -op * u
                    lanes[lx + _L_AX] += abs(v_sigma * (ca * dx + cb * dy))
                    lanes[lx + _L_AY] += abs(v_sigma * (cb * dx + cc * dy))
                st[p + _O_T] = t_cur if ok else t_old
                st[p + _O_D] = d_cur - fac_ok * cw
        if not touched:
            isect_grads[k, :] = _F0
            continue
        s_u, s_qy, s_qyy, s_qx, s_qxx, s_qxy, s_c0, s_c1, s_c2, s_c3 = _fold_lanes(lanes, mx, x0c)
        s_ax = _F0
        s_ay = _F0
        if with_abs is not None:
            s_ax, s_ay = _fold_abs(lanes)
        # v_sigma = -op * u; sums of v_sigma * (dx, dy, dx^2, dx dy, dy^2)
        s_x = -op * s_qx
        s_y = -op * s_qy
        isect_grads[k, 0] = ca * s_x + cb * s_y
        isect_grads[k, 1] = cb * s_x + cc * s_y
        isect_grads[k, 2] = -_F05 * op * s_qxx
        isect_grads[k, 3] = -op * s_qxy
        isect_grads[k, 4] = -_F05 * op * s_qyy
        isect_grads[k, 5] = s_u
        isect_grads[k, 6] = s_c0
        isect_grads[k, 7] = s_c1
        isect_grads[k, 8] = s_c2
        isect_grads[k, 9] = s_c3
        isect_grads[k, 10] = s_ax
        isect_grads[k, 11] = s_ay


@njit(cache=True, fastmath={"reassoc", "contract"})
def _fold_lanes(lanes, mx, x0c):
    """Sums over the 16 lanes of one Gaussian's per-lane sums, with lane lx's
    dx = mx - (x0c + lx) applied to the u and u dy sums.  Reassociation lets LLVM sum each
    16-lane vector with a shuffle tree (a fixed order, so results stay deterministic); the
    earlier pairwise fold through memory cost about 15 % of the backward pass."""
    s_u = _F0
    s_qy = _F0
    s_qyy = _F0
    s_qx = _F0
    s_qxx = _F0
    s_qxy = _F0
    s_c0 = _F0
    s_c1 = _F0
    s_c2 = _F0
    s_c3 = _F0
    for lx in range(np.uint64(_TS)):
        dx = mx - (x0c + _F32(lx))
        u = lanes[lx + _L_U]
        qy = lanes[lx + _L_QY]
        s_u += u
        s_qy += qy
        s_qyy += lanes[lx + _L_QYY]
        s_qx += u * dx
        s_qxx += u * dx * dx
        s_qxy += qy * dx
        s_c0 += lanes[lx + _L_C0]
        s_c1 += lanes[lx + _L_C1]
        s_c2 += lanes[lx + _L_C2]
        s_c3 += lanes[lx + _L_C3]
    return s_u, s_qy, s_qyy, s_qx, s_qxx, s_qxy, s_c0, s_c1, s_c2, s_c3


@njit(cache=True, fastmath={"reassoc", "contract"})
def _fold_abs(lanes):
    s_ax = _F0
    s_ay = _F0
    for lx in range(np.uint64(_TS)):
        s_ax += lanes[lx + _L_AX]
        s_ay += lanes[lx + _L_AY]
    return s_ax, s_ay


@njit(parallel=True, cache=True)
def rasterize_bwd(rec, backgrounds, width, height, tile_w, tile_h, tile_offsets, flatten_ids,
                  isect_rows, gauss_offsets, isect_of, order, n_workers, t_final, acc_depth,
                  last_ids, v_rgb, v_depth, v_alpha, n_colour_cams, with_abs):
    """Backward of :func:`rasterize_fwd` by reverse traversal (gsplat's scheme), given the
    gradients of its three images (``v_rgb`` [C,H,W,3], ``v_depth`` and ``v_alpha``
    [C,H,W,1]).

    Returns the gradients of means2d [C,N,2], conics [C,N,3], RGB [Cc,N,3] (``n_colour_cams``
    Cc = 1: one colour per Gaussian, summed over cameras), depths [C,N], opacities [C,N]
    (per camera) and the per-pixel absolute means2d gradients [C,N,2] (zero unless
    ``with_abs`` is an array rather than None).  Tiles are taken dynamically; each writes
    one gradient row per intersection, and the rows of a Gaussian are summed in tile order,
    so the result does not depend on the schedule or the number of threads.
    """
    n_cg = rec.shape[0]
    isect_grads = np.empty((flatten_ids.shape[0], _N_GRAD), np.float32)
    n_tiles = order.shape[0]
    counter = np.zeros(1, np.int64)
    for _w in prange(n_workers):
        st = np.empty(_BWD_FIELDS * _TP, np.float32)
        row_last = np.empty(_TS, np.int32)
        lanes = np.empty(_N_LANE_SUMS * _TS, np.float32)
        i = _atomic_fetch_add(counter, 1)
        while i < n_tiles:
            _bwd_tile(order[i], rec, backgrounds, width, height, tile_w, tile_h, tile_offsets,
                      flatten_ids, isect_rows, t_final, acc_depth, last_ids, v_rgb, v_depth,
                      v_alpha, isect_grads, st, row_last, lanes, with_abs)
            i = _atomic_fetch_add(counter, 1)
    total = np.zeros((n_cg, _N_GRAD), np.float32)
    for cg in prange(n_cg):
        for j in range(gauss_offsets[cg], gauss_offsets[cg + 1]):
            k = isect_of[j]
            for q in range(_N_GRAD):
                total[cg, q] += isect_grads[k, q]
    n_cam = backgrounds.shape[0]
    n = n_cg // n_cam
    v_means2d = np.empty((n_cam, n, 2), np.float32)
    v_conics = np.empty((n_cam, n, 3), np.float32)
    v_colours = np.zeros((n_colour_cams, n, 3), np.float32)
    v_depths = np.empty((n_cam, n), np.float32)
    v_opacities = np.empty((n_cam, n), np.float32)
    v_abs = np.empty((n_cam, n, 2), np.float32)
    for g in prange(n):
        for c in range(n_cam):
            cg = c * n + g
            cc = c if n_colour_cams > 1 else 0
            v_means2d[c, g, 0] = total[cg, 0]
            v_means2d[c, g, 1] = total[cg, 1]
            v_conics[c, g, 0] = total[cg, 2]
            v_conics[c, g, 1] = total[cg, 3]
            v_conics[c, g, 2] = total[cg, 4]
            v_opacities[c, g] = total[cg, 5]
            v_colours[cc, g, 0] += total[cg, 6]
            v_colours[cc, g, 1] += total[cg, 7]
            v_colours[cc, g, 2] += total[cg, 8]
            v_depths[c, g] = total[cg, 9]
            v_abs[c, g, 0] = total[cg, 10]
            v_abs[c, g, 1] = total[cg, 11]
    return v_means2d, v_conics, v_colours, v_depths, v_opacities, v_abs
