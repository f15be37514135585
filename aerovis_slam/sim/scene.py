"""Procedural scenes of textured planes, rendered exactly by per-pixel ray-plane intersection.

A scene is a room (floor, four walls, ceiling) with boxes standing at varied depths along the
walls, posters hanging a few centimetres in front of the walls and, in high-dynamic-range
scenes, a bright emissive window. Every surface is a textured rectangle, so a pinhole image is
exact: a pixel's ray meets plane ``k`` at inverse depth ``1/z = a_k u + b_k v + c_k`` (affine in
the pixel ``(u, v)``) and at texture coordinates given by the plane's inverse homography. The
renderer keeps, per pixel, the nearest plane (z-buffer on exact plane depth) whose rectangle
contains the hit point and samples its texture bilinearly: what ``cv2.warpPerspective`` with
``INTER_LINEAR`` does per plane, fused into numba kernels that visit each plane's pixel box
only (about 1.5 ms for a 320x240 view of a furnished room on one core).

Radiance is linear and relative: ``1.0`` is a white wall under normal room light. Lambertian
planes are scaled by the scene's global illumination ``g(t)`` (lights-off segments dim it);
emissive planes (the window: daylight from outside) are not.

World frame: z up, floor at ``z = 0``, room centred on the z axis.

Example:
    >>> from aerovis_slam.sim.rig import load_rig
    >>> scene = make_scene(3)
    >>> cam = load_rig("tiny_stereo").cameras["cam0"]
    >>> T_world_cam = np.eye(4); T_world_cam[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    >>> T_world_cam[2, 3] = 1.4
    >>> radiance, depth = scene.render(cam, T_world_cam, 0.0)
    >>> radiance.shape, bool(np.isfinite(depth).all())
    ((48, 64), True)
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numba as nb
import numpy as np

from ..calib import CameraCalibration
from ..errors import DataError

TEXEL_M = 0.012  # texture resolution on surfaces (metres per texel)
MAX_TEXTURE = 900  # texels along one side; caps memory for large walls
TEXTURE_KINDS = ("fractal", "shapes", "text", "checker", "gradient", "stripes", "plain")
PLAIN_WALL_P = 0.4  # share of room surfaces painted plain (real rooms have bare walls)
_WORDS = ("EXIT", "AERO", "VIS", "SLAM", "event", "lab", "OKVIS", "1234", "B-07", "room",
          "keypoint", "stereo", "IMU", "Jetson", "drone", "wall", "safety", "push", "pull", "kg")


# --------------------------------------------------------------------------------------------
# geometry
@dataclass
class Plane:
    """A textured rectangle ``o + s u + t v`` for ``0 <= s <= size_u``, ``0 <= t <= size_v`` (metres).

    ``u`` points right and ``v`` down as seen from the visible side, whose normal is
    ``n = v x u``. Texture texel ``(col, row)`` sits at ``s = col * size_u / (tw - 1)``,
    ``t = row * size_v / (th - 1)``.

    Attributes:
        origin: (3,) top-left corner in the world, metres.
        u, v: (3,) orthonormal in-plane axes (world).
        size_u, size_v: extent along ``u`` and ``v`` in metres.
        texture: index into :attr:`Scene.textures`.
        emissive: radiance is not scaled by the room illumination (a window).
        gain: radiance scale of this plane (emissive window brightness).
        kind: label (``wall``, ``floor``, ``ceiling``, ``box``, ``poster``, ``window``).
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    size_u: float
    size_v: float
    texture: int
    emissive: bool = False
    gain: float = 1.0
    kind: str = "wall"

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal of the visible side (world)."""
        return np.cross(self.v, self.u)

    def corners(self) -> np.ndarray:
        """(4, 3) world corners."""
        o, a, b = self.origin, self.u * self.size_u, self.v * self.size_v
        return np.stack([o, o + a, o + a + b, o + b])

    @staticmethod
    def facing(center, normal, up, size_u: float, size_v: float, texture: int, **kw) -> "Plane":
        """A rectangle centred at ``center`` whose visible side faces ``normal``; ``up`` orients its texture."""
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        up = np.asarray(up, float)
        down = -(up - n * (up @ n))
        down /= np.linalg.norm(down)
        forward = -n  # a viewer looks along -n; camera axes: right = down x forward
        right = np.cross(down, forward)
        origin = np.asarray(center, float) - right * size_u / 2 - down * size_v / 2
        return Plane(origin, right, down, float(size_u), float(size_v), texture, **kw)


@dataclass
class Illumination:
    """Global room illumination ``g(t)`` (unitless) with smooth lights-off segments.

    ``g(t) = ambient * (1 - sum_k (1 - level) * (S((t - t_off_k)/ramp) - S((t - t_on_k)/ramp)))``
    with the quintic smoothstep ``S`` (C2), so light changes are smooth like a dimmer.

    Attributes:
        ambient: base level (HDR scenes light the room dimly, e.g. 0.05).
        lights_off: list of ``(t_off_s, t_on_s)`` intervals.
        level: fraction of light left while off.
        ramp_s: duration of the dimming ramp.
    """

    ambient: float = 1.0
    lights_off: list[tuple[float, float]] = field(default_factory=list)
    level: float = 0.03
    ramp_s: float = 0.25

    @staticmethod
    def _smooth(x):
        x = np.clip(x, 0.0, 1.0)
        return x * x * x * (10 - 15 * x + 6 * x * x)

    @staticmethod
    def _dsmooth(x):
        inside = (x > 0) & (x < 1)
        return np.where(inside, 30 * x * x * (1 - x) ** 2, 0.0)

    def gain(self, t_s: float) -> float:
        """``g(t)``."""
        off = sum(self._smooth((t_s - a) / self.ramp_s) - self._smooth((t_s - b) / self.ramp_s) for a, b in self.lights_off)
        return float(self.ambient * (1 - (1 - self.level) * off))

    def dlog_gain(self, t_s: float) -> float:
        """``d log g / dt`` in 1/s (bounds the log-intensity change of lit surfaces)."""
        if not self.lights_off:
            return 0.0
        d = sum(self._dsmooth((t_s - a) / self.ramp_s) - self._dsmooth((t_s - b) / self.ramp_s) for a, b in self.lights_off)
        dg = -self.ambient * (1 - self.level) * float(d) / self.ramp_s
        return dg / self.gain(t_s)


@dataclass
class Scene:
    """Planes, their textures and the room's free space.

    Attributes:
        planes: the surfaces.
        textures: float32 (th, tw) albedo (or emitted radiance for emissive planes) arrays.
        room_lo, room_hi: (3,) room corners (world, metres).
        obstacles: list of ``(lo, hi)`` (3,) box corners the camera must not enter.
        illumination: the global light ``g(t)``.
        seed: the seed it was generated from (``None`` for hand-built scenes).
        hdr: the scene has a bright window in a dim room.
    """

    planes: list[Plane]
    textures: list[np.ndarray]
    room_lo: np.ndarray
    room_hi: np.ndarray
    obstacles: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    illumination: Illumination = field(default_factory=Illumination)
    seed: int | None = None
    hdr: bool = False

    def __post_init__(self) -> None:
        self._pack_textures()
        self._pack_planes()

    def _pack_textures(self) -> None:
        offs, flat = [], []
        n = 0
        for tex in self.textures:
            tex = np.ascontiguousarray(tex, np.float32)
            if tex.ndim != 2 or min(tex.shape) < 2:
                raise ValueError(f"textures must be 2-D with at least 2x2 texels, got shape {tex.shape}")
            offs.append(n)
            flat.append(tex.ravel())
            n += tex.size
        self._tex_flat = np.concatenate(flat) if flat else np.zeros(4, np.float32)
        self._tex_off = offs

    # -- free space -----------------------------------------------------------------------------
    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) of world points (N, 3) to the nearest wall or obstacle; negative outside free space."""
        p = np.atleast_2d(points)
        d = np.minimum((p - self.room_lo).min(axis=1), (self.room_hi - p).min(axis=1))
        for lo, hi in self.obstacles:
            # distance to an axis-aligned box (negative inside it)
            q = np.maximum(lo - p, p - hi)
            outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
            inside = np.minimum(q.max(axis=1), 0.0)
            d = np.minimum(d, outside + inside)
        return d

    # -- rendering ------------------------------------------------------------------------------
    def _pack_planes(self) -> None:
        P = len(self.planes)
        self._O = np.array([p.origin for p in self.planes], np.float64).reshape(P, 3)
        self._U = np.array([p.u for p in self.planes], np.float64).reshape(P, 3)
        self._V = np.array([p.v for p in self.planes], np.float64).reshape(P, 3)
        self._N = np.cross(self._V, self._U)
        self._corners = np.array([p.corners() for p in self.planes], np.float64).reshape(P, 4, 3)
        shapes = np.array([self.textures[p.texture].shape for p in self.planes], np.float64).reshape(P, 2)
        self._TH, self._TW = shapes[:, 0], shapes[:, 1]
        self._SU = np.array([p.size_u for p in self.planes]) / (self._TW - 1)  # metres per texel
        self._SV = np.array([p.size_v for p in self.planes]) / (self._TH - 1)
        self._OFF = np.array([self._tex_off[p.texture] for p in self.planes], np.float64)
        self._GAIN = np.array([p.gain for p in self.planes], np.float64)
        self._EMISSIVE = np.array([p.emissive for p in self.planes], np.bool_).reshape(P)
        self._corners = np.ascontiguousarray(self._corners)

    def plane_params(self, cam: CameraCalibration, T_world_cam: np.ndarray, t_s: float) -> np.ndarray:
        """Per-plane rendering coefficients for one view (float64 (P, 20), culled planes left out).

        Columns: inverse-depth coefficients ``a, b, c`` (``1/z = a u + b v + c`` at pixel
        ``(u, v)``), the 3x3 pixel-to-texel homography (row-major), texture offset, texture
        width, height, radiance gain, pixel box ``u0, u1, v0, v1`` (inclusive). Rows are sorted nearest plane first, so the renderer's
        z-test rejects most farther planes before computing their texture coordinates.
        """
        R_wc = np.ascontiguousarray(T_world_cam[:3, :3], np.float64)
        c_w = np.ascontiguousarray(T_world_cam[:3, 3], np.float64)
        out = np.empty((len(self.planes), 20), np.float64)
        n = _plane_params_kernel(self._O, self._U, self._V, self._N, self._corners, self._SU, self._SV, self._OFF,
                                 self._TW, self._TH, self._GAIN, self._EMISSIVE, R_wc, c_w, cam.fx, cam.fy, cam.cx,
                                 cam.cy, cam.width, cam.height, self.illumination.gain(t_s), out)
        return out[:n]

    def render(self, cam: CameraCalibration, T_world_cam: np.ndarray, t_s: float = 0.0,
               with_plane_index: bool = False):
        """Render linear radiance and z-depth of one camera.

        Args:
            cam: pinhole intrinsics (distortion ignored: the image is ideal pinhole).
            T_world_cam: (4, 4) camera-to-world pose.
            t_s: time in seconds (for the illumination).
            with_plane_index: also return the index (into the *visible* list) of the plane hit.

        Returns:
            radiance float32 (H, W), depth float32 (H, W) z-depth in metres (inf where no surface),
            and with ``with_plane_index`` an int32 (H, W) id of the plane seen (-1 none).
        """
        params = self.plane_params(cam, np.asarray(T_world_cam, np.float64), t_s)
        out_i = np.empty((cam.height, cam.width), np.float32)
        out_d = np.empty((cam.height, cam.width), np.float32)
        out_p = np.empty((cam.height, cam.width), np.int32)
        _render_kernel(params, self._tex_flat, out_i, out_d, out_p)
        if with_plane_index:
            return out_i, out_d, out_p
        return out_i, out_d


@nb.njit(cache=True)
def _plane_params_kernel(O, U, V, N, CORN, SU, SV, OFF, TW, TH, GAIN, EMIS, R_wc, c_w, fx, fy, cx, cy,
                         width, height, g, out):  # pragma: no cover - compiled
    """Fill ``out`` (P, 20) with the visible planes' coefficients (see :meth:`Scene.plane_params`)."""
    P = O.shape[0]
    ZN = 1e-3  # near plane (m) for clipping the pixel boxes
    dist = np.empty(P)
    keep = np.zeros(P, np.bool_)
    box = np.zeros((P, 4))
    cc = np.empty((4, 3))
    for k in range(P):
        d = N[k, 0] * (c_w[0] - O[k, 0]) + N[k, 1] * (c_w[1] - O[k, 1]) + N[k, 2] * (c_w[2] - O[k, 2])
        dist[k] = d
        if d <= 1e-9:  # back face, or the camera lies in the plane
            continue
        for m in range(4):
            for j in range(3):
                cc[m, j] = (R_wc[0, j] * (CORN[k, m, 0] - c_w[0]) + R_wc[1, j] * (CORN[k, m, 1] - c_w[1])
                            + R_wc[2, j] * (CORN[k, m, 2] - c_w[2]))
        # Pixel box of the rectangle clipped to z >= ZN: its corners in front plus the
        # crossings of its edges with the near plane (exact bound; the renderer tests each pixel).
        umin, umax, vmin, vmax = 1e18, -1e18, 1e18, -1e18
        anyv = False
        for m in range(4):
            z = cc[m, 2]
            m2 = (m + 1) % 4
            z2 = cc[m2, 2]
            for which in range(2):
                if which == 0:
                    if z <= ZN:
                        continue
                    x, y, zz = cc[m, 0], cc[m, 1], z
                else:
                    if (z - ZN) * (z2 - ZN) >= 0:
                        continue
                    lam = (ZN - z) / (z2 - z)
                    x = cc[m, 0] + lam * (cc[m2, 0] - cc[m, 0])
                    y = cc[m, 1] + lam * (cc[m2, 1] - cc[m, 1])
                    zz = ZN
                px = min(max(x * fx / zz + cx, -1e7), 1e7)
                py = min(max(y * fy / zz + cy, -1e7), 1e7)
                umin, umax, vmin, vmax = min(umin, px), max(umax, px), min(vmin, py), max(vmax, py)
                anyv = True
        if not anyv:
            continue
        u0, u1 = max(np.floor(umin) - 1, 0.0), min(np.ceil(umax) + 1, width - 1.0)
        v0, v1 = max(np.floor(vmin) - 1, 0.0), min(np.ceil(vmax) + 1, height - 1.0)
        if u0 > u1 or v0 > v1:
            continue
        keep[k] = True
        box[k, 0], box[k, 1], box[k, 2], box[k, 3] = u0, u1, v0, v1
    idx = np.flatnonzero(keep)
    order = np.argsort(dist[idx], kind="mergesort")  # nearest planes first
    n = 0
    col = np.empty((3, 3))  # camera-frame columns: u * texel, v * texel, origin
    H = np.empty((3, 3))
    for ii in order:
        k = idx[ii]
        for j in range(3):
            col[2, j] = R_wc[0, j] * (O[k, 0] - c_w[0]) + R_wc[1, j] * (O[k, 1] - c_w[1]) + R_wc[2, j] * (O[k, 2] - c_w[2])
            col[0, j] = (R_wc[0, j] * U[k, 0] + R_wc[1, j] * U[k, 1] + R_wc[2, j] * U[k, 2]) * SU[k]
            col[1, j] = (R_wc[0, j] * V[k, 0] + R_wc[1, j] * V[k, 1] + R_wc[2, j] * V[k, 2]) * SV[k]
        for c in range(3):  # H = K [u v o]
            H[0, c] = fx * col[c, 0] + cx * col[c, 2]
            H[1, c] = fy * col[c, 1] + cy * col[c, 2]
            H[2, c] = col[c, 2]
        det = (H[0, 0] * (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]) - H[0, 1] * (H[1, 0] * H[2, 2] - H[1, 2] * H[2, 0])
               + H[0, 2] * (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]))
        if abs(det) <= 1e-12:
            continue
        r = out[n]
        # Inverse homography (pixel -> texel) by the adjugate.
        r[3] = (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]) / det
        r[4] = (H[0, 2] * H[2, 1] - H[0, 1] * H[2, 2]) / det
        r[5] = (H[0, 1] * H[1, 2] - H[0, 2] * H[1, 1]) / det
        r[6] = (H[1, 2] * H[2, 0] - H[1, 0] * H[2, 2]) / det
        r[7] = (H[0, 0] * H[2, 2] - H[0, 2] * H[2, 0]) / det
        r[8] = (H[0, 2] * H[1, 0] - H[0, 0] * H[1, 2]) / det
        r[9] = (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]) / det
        r[10] = (H[0, 1] * H[2, 0] - H[0, 0] * H[2, 1]) / det
        r[11] = (H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]) / det
        # Plane n_c . X = dd in the camera; the ray X = z K^-1 (u, v, 1) gives 1/z = (K^-T n_c) . (u, v, 1) / dd.
        n0 = R_wc[0, 0] * N[k, 0] + R_wc[1, 0] * N[k, 1] + R_wc[2, 0] * N[k, 2]
        n1 = R_wc[0, 1] * N[k, 0] + R_wc[1, 1] * N[k, 1] + R_wc[2, 1] * N[k, 2]
        n2 = R_wc[0, 2] * N[k, 0] + R_wc[1, 2] * N[k, 1] + R_wc[2, 2] * N[k, 2]
        dd = n0 * col[2, 0] + n1 * col[2, 1] + n2 * col[2, 2]
        r[0] = n0 / fx / dd
        r[1] = n1 / fy / dd
        r[2] = (n2 - cx / fx * n0 - cy / fy * n1) / dd
        r[12], r[13], r[14] = OFF[k], TW[k], TH[k]
        r[15] = GAIN[k] * (1.0 if EMIS[k] else g)
        r[16], r[17], r[18], r[19] = box[k, 0], box[k, 1], box[k, 2], box[k, 3]
        n += 1
    return n


# Single-threaded on purpose: measured 2x faster than prange on a shared 2-core box.
# Plane-major with a z-buffer: each plane visits only its pixel box (nearest planes first,
# so most farther pixels fail the cheap inverse-depth test), then one pass samples textures.
@nb.njit(cache=True, fastmath=True)
def _render_kernel(params, tex, out_i, out_d, out_p):  # pragma: no cover - compiled
    height, width = out_i.shape
    n_planes = params.shape[0]
    zbuf = np.zeros((height, width))  # inverse depth of the nearest hit so far (0: none)
    sbuf = np.empty((height, width))
    tbuf = np.empty((height, width))
    out_p[:, :] = -1
    for k in range(n_planes):
        a, b, c = params[k, 0], params[k, 1], params[k, 2]
        h0, h1, h2, h3, h4, h5, h6, h7, h8 = (params[k, 3], params[k, 4], params[k, 5], params[k, 6], params[k, 7],
                                              params[k, 8], params[k, 9], params[k, 10], params[k, 11])
        smax = params[k, 13] - 0.5
        tmax = params[k, 14] - 0.5
        u0, u1, v0, v1 = int(params[k, 16]), int(params[k, 17]), int(params[k, 18]), int(params[k, 19])
        for v in range(v0, v1 + 1):
            fv = float(v)
            for u in range(u0, u1 + 1):
                fu = float(u)
                iz = a * fu + b * fv + c
                if iz > zbuf[v, u]:
                    iw = 1.0 / (h6 * fu + h7 * fv + h8)
                    s = (h0 * fu + h1 * fv + h2) * iw
                    t = (h3 * fu + h4 * fv + h5) * iw
                    # Half a texel of slack closes seams where two planes meet (round-off would
                    # otherwise let a ray slip between a wall and the ceiling); sampling clamps.
                    if s >= -0.5 and t >= -0.5 and s <= smax and t <= tmax:
                        zbuf[v, u] = iz
                        sbuf[v, u] = s
                        tbuf[v, u] = t
                        out_p[v, u] = k
    for v in range(height):
        for u in range(width):
            bp = out_p[v, u]
            if bp < 0:
                out_i[v, u] = 0.0
                out_d[v, u] = np.inf
                continue
            off = int(params[bp, 12])
            tw = int(params[bp, 13])
            th = int(params[bp, 14])
            bs = min(max(sbuf[v, u], 0.0), tw - 1.0)
            bt = min(max(tbuf[v, u], 0.0), th - 1.0)
            i0 = min(int(bs), tw - 2)
            j0 = min(int(bt), th - 2)
            fs = bs - i0
            ft = bt - j0
            base = off + j0 * tw + i0
            val = ((1.0 - fs) * (1.0 - ft) * tex[base] + fs * (1.0 - ft) * tex[base + 1]
                   + (1.0 - fs) * ft * tex[base + tw] + fs * ft * tex[base + tw + 1])
            out_i[v, u] = val * params[bp, 15]
            out_d[v, u] = 1.0 / zbuf[v, u]


# --------------------------------------------------------------------------------------------
# textures
def _fractal(rng: np.random.Generator, h: int, w: int, cell: float, octaves: int = 5) -> np.ndarray:
    """Multi-octave value noise in [0, 1] (float32 (h, w)); ``cell`` = largest feature in texels."""
    out = np.zeros((h, w), np.float32)
    amp = 1.0
    for _ in range(octaves):
        gh, gw = max(2, int(h / cell) + 2), max(2, int(w / cell) + 2)
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        amp *= 0.55
        cell = max(cell / 2.0, 4.0)  # no detail below ~4 texels (see make_texture)
    lo, hi = np.percentile(out, [1, 99])
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0, 1)


def make_texture(rng: np.random.Generator, h: int, w: int, kind: str | None = None) -> np.ndarray:
    """A procedural albedo texture, float32 (h, w) in [0.06, 0.9], band-limited (blurred ~1 texel).

    Kinds: ``fractal`` noise, random filled ``shapes``, ``text``-like clutter, ``checker``,
    smooth ``gradient``, ``stripes`` (long straight edges) and ``plain`` paint (only when asked
    for; ``kind=None`` draws one of the others).
    """
    kind = kind or TEXTURE_KINDS[rng.integers(len(TEXTURE_KINDS) - 1)]  # "plain" only on request
    m = min(h, w)
    if kind == "plain":  # painted wall: smooth, low-contrast shading
        img = rng.uniform(0.45, 0.85) + 0.1 * (_fractal(rng, h, w, cell=rng.uniform(40, 120), octaves=3) - 0.5)
    elif kind == "fractal":
        img = _fractal(rng, h, w, cell=rng.uniform(15, 60))
    elif kind == "shapes":
        # OpenCV draws on 8-bit canvases (putText requires it in OpenCV 5); 255 levels suffice.
        canvas = np.full((h, w), int(rng.uniform(0.3, 0.8) * 255), np.uint8)
        for _ in range(int(rng.integers(8, 30))):
            c = int(rng.integers(0, 256))
            cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
            r = int(rng.uniform(0.03, 0.2) * m) + 2
            shape = rng.integers(4)
            if shape == 0:
                cv2.rectangle(canvas, (cx - r, cy - r // 2), (cx + r, cy + r), c, -1)
            elif shape == 1:
                cv2.circle(canvas, (cx, cy), r, c, -1, lineType=cv2.LINE_AA)
            elif shape == 2:
                cv2.ellipse(canvas, (cx, cy), (r, max(1, r // 2)), float(rng.uniform(0, 180)), 0, 360, c, -1, lineType=cv2.LINE_AA)
            else:
                pts = (rng.uniform(-r, r, (3, 2)) + [cx, cy]).astype(np.int32)
                cv2.fillPoly(canvas, [pts], c, lineType=cv2.LINE_AA)
        img = canvas.astype(np.float32) / 255.0
    elif kind == "text":
        canvas = np.full((h, w), int(rng.uniform(0.6, 0.9) * 255), np.uint8)
        ink = int(rng.uniform(0.1, 0.4) * 255)
        scale = rng.uniform(0.4, 1.2)
        step = int(30 * scale * rng.uniform(1.2, 2.5)) + 4  # line spacing: text-like clutter, not a wall of text
        for y in range(step, h, step):
            x = int(rng.integers(0, step))
            while x < w:
                word = _WORDS[rng.integers(len(_WORDS))]
                cv2.putText(canvas, word, (x, y), int(rng.choice([0, 2, 3, 4])), scale, ink, max(1, int(2 * scale)), cv2.LINE_AA)
                x += int(len(word) * 22 * scale) + int(rng.integers(5, 120))
        img = canvas.astype(np.float32) / 255.0
    elif kind == "checker":
        cell = int(rng.uniform(8, 30))
        a, b = rng.uniform(0.05, 0.4), rng.uniform(0.55, 0.95)
        yy, xx = np.mgrid[0:h, 0:w]
        img = np.where(((yy // cell) + (xx // cell)) % 2 == 0, a, b).astype(np.float32)
    elif kind == "gradient":
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        ang = rng.uniform(0, 2 * np.pi)
        lin = (np.cos(ang) * xx + np.sin(ang) * yy) / max(h, w)
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        rad = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * (0.3 * m) ** 2))
        img = lin - lin.min()
        img = 0.7 * img / max(img.max(), 1e-6) + 0.3 * rad
        img += 0.15 * _fractal(rng, h, w, cell=80, octaves=2)
        img = (img - img.min()) / max(img.max() - img.min(), 1e-6)
    elif kind == "stripes":
        img = np.empty((h, w), np.float32)
        horizontal = rng.random() < 0.5
        n = h if horizontal else w
        pos = 0
        vals = np.empty(n, np.float32)
        while pos < n:
            width_ = int(rng.integers(4, 40))
            vals[pos:pos + width_] = rng.uniform(0, 1)
            pos += width_
        img[:] = vals[:, None] if horizontal else vals[None, :]
    else:
        raise ValueError(f"unknown texture kind {kind!r}; expected one of {TEXTURE_KINDS}")
    if kind not in ("gradient", "plain"):  # gentle large-scale shading so no two surfaces look identical
        img = img * (0.75 + 0.25 * _fractal(rng, h, w, cell=120, octaves=2))
    img = np.clip(0.06 + 0.84 * img, 0.06, 0.9).astype(np.float32)
    # Band-limit: the renderer samples bilinearly without mip-mapping, so detail finer than
    # a few texels would alias (flicker and spurious events) when surfaces are seen from afar.
    return cv2.GaussianBlur(img, (0, 0), 1.5)


#: Photographs bundled with scikit-image (public domain or CC0, per its data README) that show real
#: scenes and surfaces: posters with natural image statistics, which procedural textures lack.
PHOTO_TEXTURES = ("astronaut", "brick", "camera", "chelsea", "coffee", "coins", "grass", "gravel", "page", "rocket", "text")
PHOTO_PREFIX = "skimage:"


def photo_texture_path(name: str) -> Path:
    """The file of a scikit-image photograph (``skimage:coffee`` or ``coffee``), read without importing skimage.

    Raises:
        DataError: scikit-image is not installed (it comes with the ``train`` extra), or no such photograph.
    """
    import importlib.util

    name = name[len(PHOTO_PREFIX):] if name.startswith(PHOTO_PREFIX) else name
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        raise DataError(None, f"texture {PHOTO_PREFIX}{name}: scikit-image is not installed (pip install -e '.[train]')")
    folder = Path(next(iter(spec.submodule_search_locations))) / "data"
    found = sorted(folder.glob(f"{name}.*"))
    if not found:
        raise DataError(folder, f"no photograph {name!r} (scikit-image's data holds {sorted(p.stem for p in folder.glob('*.png'))})")
    return found[0]


def load_texture_image(path: str | os.PathLike, max_side: int = MAX_TEXTURE) -> np.ndarray:
    """A user image (or ``skimage:NAME``, one of :data:`PHOTO_TEXTURES`) as an albedo texture (float32 in [0.06, 0.9]).

    Raises:
        DataError: when the file is missing or not a readable image.
    """
    p = photo_texture_path(str(path)) if str(path).startswith(PHOTO_PREFIX) else Path(path)
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) if p.is_file() else None
    if img is None:
        raise DataError(p, "cannot read texture image (missing, unreadable or not an image format OpenCV decodes)")
    s = max_side / max(img.shape)
    if s < 1:
        img = cv2.resize(img, (max(2, int(img.shape[1] * s)), max(2, int(img.shape[0] * s))), interpolation=cv2.INTER_AREA)
    img = img.astype(np.float32) / 255.0
    return cv2.GaussianBlur(np.clip(0.06 + 0.84 * img, 0.06, 0.9), (0, 0), 1.0)


def _tex_shape(size_u: float, size_v: float, texel: float = TEXEL_M) -> tuple[int, int]:
    s = min(1.0, MAX_TEXTURE / (max(size_u, size_v) / texel))
    return max(2, int(size_v / texel * s) + 1), max(2, int(size_u / texel * s) + 1)


def _window_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Daylight seen through a window: bright sky and clouds, darker mullions (relative radiance)."""
    yy = np.linspace(0, 1, h, dtype=np.float32)[:, None]
    sky = 0.6 + 0.4 * (1 - yy) + 0.3 * _fractal(rng, h, w, cell=40, octaves=4)
    horizon = int(h * rng.uniform(0.55, 0.8))
    sky[horizon:] = 0.15 + 0.25 * _fractal(rng, h - horizon, w, cell=20, octaves=4)  # trees/buildings
    bar = max(2, min(h, w) // 25)
    sky[:, w // 2 - bar // 2: w // 2 + bar // 2 + 1] = 0.02  # mullions
    sky[h // 2 - bar // 2: h // 2 + bar // 2 + 1, :] = 0.02
    sky[:bar], sky[-bar:], sky[:, :bar], sky[:, -bar:] = 0.02, 0.02, 0.02, 0.02
    return cv2.GaussianBlur(sky.astype(np.float32), (0, 0), 1.0)


# --------------------------------------------------------------------------------------------
# scene generation
def make_scene(
    seed: int,
    *,
    hdr: bool = False,
    lights_off: list[tuple[float, float]] | None = None,
    user_textures: list[str | os.PathLike] | None = None,
    n_boxes: tuple[int, int] = (3, 7),
) -> Scene:
    """Generate a furnished room from a seed (the same seed always gives the same scene).

    Args:
        seed: scene seed.
        hdr: dim room (ambient 0.05) with a bright window (radiance ~30-150): about 4-5
            decades between the darkest albedo in the room and the sky.
        lights_off: ``(t_off_s, t_on_s)`` intervals in which the room light drops to 3 %.
        user_textures: image files used (cyclically) for the posters instead of procedural ones.
        n_boxes: range of the number of boxes.

    Returns:
        The scene. The free space (where cameras may go) is the room shrunk by the band along
        the walls in which boxes stand.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CE7E]))
    user = [load_texture_image(p) for p in (user_textures or [])]
    X, Y, H = rng.uniform(3.0, 4.5), rng.uniform(2.5, 4.0), rng.uniform(2.6, 3.4)
    lo, hi = np.array([-X, -Y, 0.0]), np.array([X, Y, H])
    textures: list[np.ndarray] = []
    planes: list[Plane] = []

    def add(center, normal, up, su, sv, kind, tex=None, **kw):
        if tex is None:
            plain = kind in ("wall", "floor", "ceiling") and rng.random() < PLAIN_WALL_P
            tex = make_texture(rng, *_tex_shape(su, sv), kind="plain" if plain else None)
        textures.append(tex)
        planes.append(Plane.facing(center, normal, up, su, sv, len(textures) - 1, kind=kind, **kw))

    # Room: normals point inwards.
    # Horizontal planes: "up" along +y puts the texture's v (down) along -y and u along +-x.
    add([0, 0, 0], [0, 0, 1], [0, 1, 0], 2 * X, 2 * Y, "floor")
    add([0, 0, H], [0, 0, -1], [0, 1, 0], 2 * X, 2 * Y, "ceiling")
    walls = [([X, 0, H / 2], [-1, 0, 0], 2 * Y), ([-X, 0, H / 2], [1, 0, 0], 2 * Y),
             ([0, Y, H / 2], [0, -1, 0], 2 * X), ([0, -Y, H / 2], [0, 1, 0], 2 * X)]
    for c, n, length in walls:
        add(c, n, [0, 0, 1], length, H, "wall")

    # Boxes stand in a band of width BAND along the walls, leaving the centre free.
    band = 1.2
    obstacles = []
    for _ in range(int(rng.integers(n_boxes[0], n_boxes[1] + 1))):
        sx, sy, sz = rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.6)
        wall = rng.integers(4)
        gap = rng.uniform(0.05, band - max(sx, sy) - 0.05) if band - max(sx, sy) > 0.1 else 0.05
        if wall < 2:  # along x = +-X
            cx = (X - gap - sx / 2) * (1 if wall == 0 else -1)
            cy = rng.uniform(-Y + sy / 2, Y - sy / 2)
        else:
            cy = (Y - gap - sy / 2) * (1 if wall == 2 else -1)
            cx = rng.uniform(-X + sx / 2, X - sx / 2)
        blo, bhi = np.array([cx - sx / 2, cy - sy / 2, 0.0]), np.array([cx + sx / 2, cy + sy / 2, sz])
        obstacles.append((blo, bhi))
        mid = (blo + bhi) / 2
        tex_kind = TEXTURE_KINDS[rng.integers(len(TEXTURE_KINDS) - 1)]
        for axis in range(3):
            for sign in (-1, 1):
                if axis == 2 and sign < 0:
                    continue  # bottom face rests on the floor
                n = np.zeros(3)
                n[axis] = sign
                c = mid.copy()
                c[axis] = bhi[axis] if sign > 0 else blo[axis]
                dims = bhi - blo
                if axis == 2:
                    su, sv, up = dims[0], dims[1], [0, 1, 0]
                else:
                    su, sv, up = dims[1 - axis], dims[2], [0, 0, 1]
                add(c, n, up, su, sv, "box", tex=make_texture(rng, *_tex_shape(su, sv), kind=tex_kind))

    # Posters 2 cm in front of the walls, some with user images.
    n_posters = int(rng.integers(2, 6)) if not user else max(len(user), 2)
    for i in range(n_posters):
        c, n, length = walls[rng.integers(4)]
        n = np.asarray(n, float)
        along = np.cross(n, [0, 0, 1])
        su = rng.uniform(0.4, 1.4)
        sv = rng.uniform(0.4, 1.0)
        if user:
            img = user[i % len(user)]
            sv = su * img.shape[0] / img.shape[1]
            tex = img
        else:
            tex = None
        center = np.asarray(c, float) + n * 0.02 + along * rng.uniform(-length / 2 + su, length / 2 - su)
        center[2] = rng.uniform(0.9, min(2.2, H - sv / 2 - 0.05))
        add(center, n, [0, 0, 1], su, sv, "poster", tex=tex)

    illumination = Illumination(ambient=0.05 if hdr else 1.0, lights_off=list(lights_off or []))
    if hdr:
        c, n, length = walls[rng.integers(4)]
        n = np.asarray(n, float)
        su, sv = rng.uniform(1.0, 1.8), rng.uniform(0.8, 1.3)
        center = np.asarray(c, float) + n * 0.01 + np.cross(n, [0, 0, 1]) * rng.uniform(-0.8, 0.8)
        center[2] = 1.5
        th, tw = _tex_shape(su, sv)
        add(center, n, [0, 0, 1], su, sv, "window", tex=_window_texture(rng, th, tw),
            emissive=True, gain=float(rng.uniform(30, 150)))

    return Scene(planes, textures, lo, hi, obstacles, illumination, seed=int(seed), hdr=hdr)


def free_space(scene: Scene, margin: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners of the central box where a camera can move freely (no boxes, ``margin`` to surfaces)."""
    band = 1.2
    lo = scene.room_lo + np.array([band + margin, band + margin, margin])
    hi = scene.room_hi - np.array([band + margin, band + margin, margin])
    return lo, hi
