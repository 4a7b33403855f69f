"""Built-in procedural scenes: analytic ray casting of planes, boxes, spheres, cylinders and thin rods.

Scene ``i`` of seed ``s`` is always the same scene: its parameters come from
``numpy.random.default_rng([s, i])`` and nothing else. A pinhole camera at the origin looks along +z
(x right, y down); the horizontal field of view defaults to 63.5 deg (ToF-FlyingThings3D's). Rendering is
vectorised over pixels with per-object screen-space culling (a 640x480 scene takes a few tens of ms).

Outputs per scene:
- clean z-depth in mm (the camera's z, not the ray length);
- a radiometric amplitude [1/m^2] = (reflectance * cos(incidence) + specular lobe) / (range_m)^2 (emitter next
  to the lens, inverse-square fall-off; ``tofdenoise.physics.photometry`` turns it into electrons);
- a validity mask: pixels that see no surface (an opening in the back wall: open background beyond the working
  range) and pixels beyond ``max_depth_mm`` or nearer than ``min_depth_mm`` are invalid.

Surfaces a camera gets no usable return from (renderer 2; the geometry of scene i is unchanged, the materials
come from a second random stream ``default_rng([s, i, 2])``):
- black absorbers (reflectance 0.3-1.5 %, e.g. black velvet or foam at 850 nm) on some objects and walls;
- specular surfaces (a dim diffuse part plus a narrow lobe rho_s cos^n(theta) towards the co-located emitter):
  they saturate where they face the camera and return almost nothing elsewhere;
- an opening in the back wall on some scenes (a window or a door to a far room): no ground truth there.
Which of them become holes is decided by the camera (signal threshold, full well), not here.

Depths stay inside [min_depth_mm, max_depth_mm]. Configured through the datamodule (``data.source_kwargs``,
``ProceduralSource.from_config``), ``max_depth_mm`` defaults to ``max_depth_fraction`` (80 %) of the
calibration's unambiguous range so that no scene would wrap in phase, and the seed is ``data.seed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tofdenoise.data_modules.sources.base import (
    RawSample,
    SourceContext,
    depth_validity,
    init_keywords,
    register_source,
)

DEFAULT_HFOV_DEG = 63.5
#: the deepest scene depth as a fraction of the calibration's unambiguous range (``max_depth_fraction``)
DEFAULT_MAX_DEPTH_FRACTION = 0.8
#: the nearest scene depth [mm] (``min_depth_mm``): the training scenes and the simulated capture sets start here
DEFAULT_MIN_DEPTH_MM = 300.0


def focal_length_px(width: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> float:
    """Pinhole focal length in pixels for a horizontal field of view: f = (W/2) / tan(HFOV/2)."""
    return (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)


def pixel_rays(height: int, width: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image coordinates (x/z, y/z) of pixel centres, each (H, W) float32."""
    f = focal_length_px(width, hfov_deg)
    xs = ((np.arange(width, dtype=np.float64) + 0.5 - width / 2.0) / f).astype(np.float32)
    ys = ((np.arange(height, dtype=np.float64) + 0.5 - height / 2.0) / f).astype(np.float32)
    return np.broadcast_to(xs[None, :], (height, width)), np.broadcast_to(ys[:, None], (height, width))


# ---------------------------------------------------------------- reflectance textures
@dataclass(frozen=True)
class Texture:
    """Reflectance r(p) = clip(base * (1 + contrast * pattern(p)), min_albedo, 1) with p the 3-D point in mm, plus
    an optional specular lobe ``specular`` * cos^``shininess``(incidence) (0: a Lambertian surface)."""

    base: float
    kind: str  # "uniform" | "stripes" | "checker" | "waves"
    contrast: float
    period_mm: float
    direction: tuple[float, float, float]
    phases: tuple[float, float, float]
    min_albedo: float = 0.02
    specular: float = 0.0
    shininess: float = 1.0

    def albedo(self, px: np.ndarray, py: np.ndarray, pz: np.ndarray) -> np.ndarray:
        if self.kind == "uniform":
            pattern = np.zeros_like(px)
        else:
            k = 2.0 * math.pi / self.period_mm
            a, b, c = self.direction
            proj = (a * px + b * py + c * pz) * k
            if self.kind == "stripes":
                pattern = np.sin(proj + self.phases[0])
            elif self.kind == "checker":
                pattern = np.sign(
                    np.sin(px * k + self.phases[0]) * np.sin(py * k + self.phases[1]) * np.sin(pz * k + self.phases[2])
                    + 1e-6
                )
            else:  # waves: a smooth, non-periodic-looking mix
                pattern = np.sin(proj + self.phases[0]) * np.cos(0.37 * k * px + self.phases[1]) + 0.5 * np.sin(
                    0.61 * k * (py - pz) + self.phases[2]
                )
        return np.clip(self.base * (1.0 + self.contrast * pattern), self.min_albedo, 1.0).astype(np.float32)

    def lobe(self, cos_incidence: np.ndarray) -> np.ndarray:
        """Specular return rho_s cos^n(theta) (emitter and camera share the half vector: it peaks at theta = 0)."""
        if self.specular <= 0:
            return np.zeros_like(cos_incidence)
        return (self.specular * np.clip(cos_incidence, 0.0, 1.0) ** self.shininess).astype(np.float32)


def random_texture(rng: np.random.Generator) -> Texture:
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction) + 1e-12
    return Texture(
        base=float(math.exp(rng.uniform(math.log(0.06), math.log(0.95)))),
        kind=str(rng.choice(["uniform", "stripes", "checker", "waves"], p=[0.3, 0.25, 0.2, 0.25])),
        contrast=float(rng.uniform(0.2, 0.8)),
        period_mm=float(rng.uniform(15.0, 200.0)),
        direction=tuple(float(v) for v in direction),
        phases=tuple(float(v) for v in rng.uniform(0, 2 * math.pi, size=3)),
    )


def absorber_texture(rng: np.random.Generator) -> Texture:
    """A black absorber: reflectance 0.3-1.5 % with a faint texture."""
    return Texture(
        base=float(rng.uniform(0.003, 0.015)),
        kind="uniform",
        contrast=0.0,
        period_mm=100.0,
        direction=(1.0, 0.0, 0.0),
        phases=(0.0, 0.0, 0.0),
        min_albedo=0.001,
    )


def specular_texture(rng: np.random.Generator, diffuse: Texture) -> Texture:
    """A glossy surface: a dim diffuse part (5-25 % of ``diffuse``'s) and a narrow bright lobe."""
    return Texture(
        base=diffuse.base * float(rng.uniform(0.05, 0.25)),
        kind=diffuse.kind,
        contrast=diffuse.contrast,
        period_mm=diffuse.period_mm,
        direction=diffuse.direction,
        phases=diffuse.phases,
        min_albedo=0.002,
        specular=float(math.exp(rng.uniform(math.log(3.0), math.log(40.0)))),
        shininess=float(math.exp(rng.uniform(math.log(30.0), math.log(400.0)))),
    )


# Shares of the surfaces that return (almost) nothing usable; drawn from the scene's material stream
ABSORBER_SHARE = 0.12
SPECULAR_SHARE = 0.12
OPENING_SHARE = 0.35


def assign_materials(prims: list[Any], rng: np.random.Generator) -> list[Any]:
    """Replace the texture of some primitives by a black absorber or a specular material (the back wall is
    never an absorber: a whole-frame hole teaches nothing)."""
    out = []
    for k, prim in enumerate(prims):
        u = rng.random()
        texture = prim.texture
        if u < ABSORBER_SHARE and k > 0:
            texture = absorber_texture(rng)
        elif u < ABSORBER_SHARE + SPECULAR_SHARE:
            texture = specular_texture(rng, texture)
        else:
            rng.random()  # keep the stream aligned whatever the choice
        out.append(replace(prim, texture=texture))
    return out


@dataclass(frozen=True)
class Opening:
    """A window in the back wall, in normalised image coordinates x/z in [x0, x1], y/z in [y0, y1]: rays through
    it see no surface of the room (the open background beyond the working range)."""

    x0: float
    x1: float
    y0: float
    y1: float

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (x >= self.x0) & (x <= self.x1) & (y >= self.y0) & (y <= self.y1)


def random_opening(rng: np.random.Generator, xmax: float, ymax: float) -> Opening | None:
    """With probability OPENING_SHARE an opening covering 4-25 % of the frame, anywhere in it."""
    if rng.random() >= OPENING_SHARE:
        rng.random(4)
        return None
    area = rng.uniform(0.04, 0.25)
    aspect = math.exp(rng.uniform(math.log(0.5), math.log(2.0)))
    w = min(2 * xmax, math.sqrt(area * 4 * xmax * ymax * aspect))
    h = min(2 * ymax, area * 4 * xmax * ymax / w)
    cx, cy = rng.uniform(-xmax + w / 2, xmax - w / 2), rng.uniform(-ymax + h / 2, ymax - h / 2)
    rng.random(2)
    return Opening(float(cx - w / 2), float(cx + w / 2), float(cy - h / 2), float(cy + h / 2))


# ---------------------------------------------------------------- primitives
# Every intersect(x, y) takes the normalised ray directions d = (x, y, 1) of a pixel window and returns
# (t, nx, ny, nz): the hit's z-depth (inf = miss) and the unnormalised surface normal.
Hit = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
_INF = np.float32(np.inf)


@dataclass(frozen=True)
class InverseDepthPlane:
    """Plane g . p = 1 with g = (gx, gy, g0): its z-depth along ray (x, y, 1) is 1 / (gx x + gy y + g0)."""

    g: tuple[float, float, float]
    texture: Texture
    opening: Opening | None = None

    def intersect(self, x: np.ndarray, y: np.ndarray) -> Hit:
        gx, gy, g0 = self.g
        denom = gx * x + gy * y + g0
        with np.errstate(divide="ignore"):
            t = np.where(denom > 1e-9, 1.0 / np.maximum(denom, 1e-12), _INF).astype(np.float32)
        if self.opening is not None:
            t = np.where(self.opening.contains(x, y), _INF, t).astype(np.float32)
        n = np.ones_like(x)
        return t, gx * n, gy * n, g0 * n

    def bounds(self) -> None:
        return None


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    texture: Texture

    def intersect(self, x: np.ndarray, y: np.ndarray) -> Hit:
        cx, cy, cz = self.center
        dd = x * x + y * y + 1.0
        dc = x * cx + y * cy + cz
        cc = cx * cx + cy * cy + cz * cz - self.radius**2
        disc = dc * dc - dd * cc
        hit = disc >= 0
        t = np.where(hit, (dc - np.sqrt(np.maximum(disc, 0.0))) / dd, _INF).astype(np.float32)
        t = np.where(t > 0, t, _INF)
        return t, x * t - cx, y * t - cy, t - cz

    def bounds(self) -> tuple[tuple[float, float, float], float]:
        return self.center, self.radius


@dataclass(frozen=True)
class Box:
    """Oriented box: centre, rotation matrix R (columns = box axes in camera frame), half sizes."""

    center: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]
    half: tuple[float, float, float]
    texture: Texture

    def intersect(self, x: np.ndarray, y: np.ndarray) -> Hit:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            return self._intersect(x, y)

    def _intersect(self, x: np.ndarray, y: np.ndarray) -> Hit:
        r = np.asarray(self.rotation, dtype=np.float32)
        c = np.asarray(self.center, dtype=np.float32)
        origin = -(r.T @ c)  # camera origin in box frame
        t_near = np.full(x.shape, -np.inf, dtype=np.float32)
        t_far = np.full(x.shape, np.inf, dtype=np.float32)
        axis_near = np.zeros(x.shape, dtype=np.int8)
        sign_near = np.zeros(x.shape, dtype=np.float32)
        for k in range(3):
            dk = r[0, k] * x + r[1, k] * y + r[2, k]
            safe = np.where(np.abs(dk) < 1e-9, np.float32(1e-9), dk)
            t1 = (-self.half[k] - origin[k]) / safe
            t2 = (self.half[k] - origin[k]) / safe
            lo = np.minimum(t1, t2)
            hi = np.maximum(t1, t2)
            better = lo > t_near
            axis_near = np.where(better, k, axis_near)
            sign_near = np.where(better, -np.sign(safe), sign_near)
            t_near = np.maximum(t_near, lo)
            t_far = np.minimum(t_far, hi)
        hit = (t_near <= t_far) & (t_near > 0)
        t = np.where(hit, t_near, _INF).astype(np.float32)
        nx = np.zeros_like(x)
        ny = np.zeros_like(x)
        nz = np.zeros_like(x)
        for k in range(3):
            sel = (axis_near == k) * sign_near
            nx = nx + sel * r[0, k]
            ny = ny + sel * r[1, k]
            nz = nz + sel * r[2, k]
        return t, nx, ny, nz

    def bounds(self) -> tuple[tuple[float, float, float], float]:
        return self.center, float(np.linalg.norm(self.half))


@dataclass(frozen=True)
class Cylinder:
    """Finite capped cylinder: centre, unit axis, radius, half length (thin rods are cylinders too)."""

    center: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float
    half_length: float
    texture: Texture

    def intersect(self, x: np.ndarray, y: np.ndarray) -> Hit:
        with np.errstate(invalid="ignore", over="ignore"):
            return self._intersect(x, y)

    def _intersect(self, x: np.ndarray, y: np.ndarray) -> Hit:
        cx, cy, cz = self.center
        ax, ay, az = self.axis
        # ray p = t d, d = (x, y, 1); w = -c
        d_a = x * ax + y * ay + az
        w_a = -(cx * ax + cy * ay + cz * az)
        dpx, dpy, dpz = x - d_a * ax, y - d_a * ay, 1.0 - d_a * az
        wpx, wpy, wpz = -cx - w_a * ax, -cy - w_a * ay, -cz - w_a * az
        qa = dpx * dpx + dpy * dpy + dpz * dpz
        qb = 2.0 * (dpx * wpx + dpy * wpy + dpz * wpz)
        qc = wpx * wpx + wpy * wpy + wpz * wpz - self.radius**2
        disc = qb * qb - 4.0 * qa * qc
        ok = (disc >= 0) & (qa > 1e-12)
        t_side = np.where(ok, (-qb - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * np.maximum(qa, 1e-12)), _INF)
        h = t_side * d_a + w_a  # axial coordinate of the hit relative to the centre
        t_side = np.where((np.abs(h) <= self.half_length) & (t_side > 0), t_side, _INF).astype(np.float32)
        # caps: planes (p - c) . a = +-L/2
        t_cap = np.full(x.shape, np.inf, dtype=np.float32)
        cap_sign = np.zeros(x.shape, dtype=np.float32)
        safe = np.where(np.abs(d_a) < 1e-9, np.float32(1e-9), d_a)
        for s in (-1.0, 1.0):
            tc = (s * self.half_length - w_a) / safe
            px, py, pz = tc * x - cx, tc * y - cy, tc - cz
            along = px * ax + py * ay + pz * az
            radial2 = px * px + py * py + pz * pz - along * along
            good = (tc > 0) & (radial2 <= self.radius**2) & (tc < t_cap)
            t_cap = np.where(good, tc, t_cap)
            cap_sign = np.where(good, s, cap_sign)
        use_cap = t_cap < t_side
        t = np.where(use_cap, t_cap, t_side).astype(np.float32)
        # side normal = radial component of (p - c)
        px, py, pz = t * x - cx, t * y - cy, t - cz
        along = px * ax + py * ay + pz * az
        nx = np.where(use_cap, cap_sign * ax, px - along * ax)
        ny = np.where(use_cap, cap_sign * ay, py - along * ay)
        nz = np.where(use_cap, cap_sign * az, pz - along * az)
        return t, nx, ny, nz

    def bounds(self) -> tuple[tuple[float, float, float], float]:
        return self.center, math.hypot(self.radius, self.half_length)


def _random_rotation(rng: np.random.Generator, max_tilt: float = 0.6) -> np.ndarray:
    """Rotation about y (any angle) followed by a moderate tilt about x and z."""
    yaw = rng.uniform(0, 2 * math.pi)
    pitch, roll = rng.uniform(-max_tilt, max_tilt, size=2)
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return rz @ rx @ ry


# ---------------------------------------------------------------- scene generation
@dataclass(frozen=True)
class SceneSpec:
    height: int
    width: int
    hfov_deg: float
    min_depth_mm: float
    max_depth_mm: float
    primitives: tuple[Any, ...]


def generate_scene(
    seed: int,
    index: int,
    height: int,
    width: int,
    min_depth_mm: float,
    max_depth_mm: float,
    hfov_deg: float = DEFAULT_HFOV_DEG,
) -> SceneSpec:
    """Draw scene ``index`` of ``seed``: a slanted back wall, optional floor / side wall, 4-9 objects."""
    if not 0 < min_depth_mm < max_depth_mm:
        raise ValueError(f"procedural scenes need 0 < min_depth_mm < max_depth_mm, got {min_depth_mm}, {max_depth_mm}")
    rng = np.random.default_rng([int(seed), int(index)])
    f = focal_length_px(width, hfov_deg)
    xmax = (width / 2.0) / f
    ymax = (height / 2.0) / f
    z_lo, z_hi = float(min_depth_mm), float(max_depth_mm)
    prims: list[Any] = []

    # back wall: inverse depth affine in (x, y); its farthest corner stays at <= z_hi
    z_wall = rng.uniform(max(0.5 * z_hi, 2.5 * z_lo), 0.95 * z_hi) if 2.5 * z_lo < 0.95 * z_hi else 0.95 * z_hi
    g0 = 1.0 / z_wall
    slack = g0 - 1.0 / z_hi
    share = rng.dirichlet([1.0, 1.0]) * rng.uniform(0.3, 0.97)
    gx = float(rng.choice([-1, 1]) * share[0] * slack / xmax)
    gy = float(rng.choice([-1, 1]) * share[1] * slack / ymax)
    prims.append(InverseDepthPlane((gx, gy, g0), random_texture(rng)))

    # floor (y = h below the camera) and a side wall (x = +-w), placed so that they never come nearer than z_lo
    if rng.random() < 0.6:
        h = rng.uniform(1.05 * z_lo * ymax, 0.9 * z_wall * ymax)
        prims.append(InverseDepthPlane((0.0, 1.0 / h, 0.0), random_texture(rng)))
    if rng.random() < 0.4:
        w = rng.uniform(1.05 * z_lo * xmax, 0.9 * z_wall * xmax)
        s = float(rng.choice([-1.0, 1.0]))
        prims.append(InverseDepthPlane((s / w, 0.0, 0.0), random_texture(rng)))

    n_objects = int(rng.integers(4, 10))
    for _ in range(n_objects):
        kind = rng.choice(["sphere", "box", "cylinder", "rod", "plate"], p=[0.22, 0.28, 0.2, 0.18, 0.12])
        z_room = 0.92 * z_wall - 1.05 * z_lo
        size = rng.uniform(0.04, 0.16) * z_wall
        size = min(size, 0.45 * z_room)  # bounding radius must fit between z_lo and the wall
        z_c = rng.uniform(1.05 * z_lo + size, 0.92 * z_wall - 0.3 * size)
        x_c = rng.uniform(-0.85, 0.85) * xmax * z_c
        y_c = rng.uniform(-0.85, 0.85) * ymax * z_c
        center = (float(x_c), float(y_c), float(z_c))
        texture = random_texture(rng)
        if kind == "sphere":
            prims.append(Sphere(center, float(size), texture))
        elif kind == "box":
            half = tuple(float(v) for v in rng.uniform(0.35, 1.0, size=3) * size / math.sqrt(3.0))
            prims.append(Box(center, tuple(map(tuple, _random_rotation(rng))), half, texture))
        elif kind == "plate":  # a thin slab: sharp-edged, nearly planar structure
            half = (
                float(size * rng.uniform(0.5, 0.7)),
                float(size * rng.uniform(0.5, 0.7)),
                float(rng.uniform(2.0, 8.0)),
            )
            prims.append(Box(center, tuple(map(tuple, _random_rotation(rng, 1.0))), half, texture))
        else:
            axis = _random_rotation(rng, 0.5 if kind == "cylinder" else 1.2)[:, 1]
            if kind == "cylinder":
                radius, half_len = size * rng.uniform(0.35, 0.7), size * rng.uniform(0.5, 0.9)
            else:  # thin rod: a few mm to ~1.5 cm, long
                radius, half_len = rng.uniform(3.0, 15.0), size * rng.uniform(1.5, 3.0)
                half_len = min(half_len, 0.95 * (z_c - 1.05 * z_lo) / max(abs(float(axis[2])), 1e-3), half_len)
            prims.append(Cylinder(center, tuple(float(v) for v in axis), float(radius), float(half_len), texture))
    materials = np.random.default_rng([int(seed), int(index), 2])
    prims = assign_materials(prims, materials)
    opening = random_opening(materials, xmax, ymax)
    if opening is not None:
        prims[0] = replace(prims[0], opening=opening)
    return SceneSpec(height, width, hfov_deg, z_lo, z_hi, tuple(prims))


def _screen_window(bounds, f: float, height: int, width: int, z_lo: float):
    """Conservative pixel window (v0, v1, u0, u1) of a bounding sphere, or None when it is off screen."""
    (cx, cy, cz), r = bounds
    near = cz - r
    if near <= 0.05 * z_lo:
        return 0, height, 0, width
    lo_x = min((cx - r) / near, (cx - r) / (cz + r))
    hi_x = max((cx + r) / near, (cx + r) / (cz + r))
    lo_y = min((cy - r) / near, (cy - r) / (cz + r))
    hi_y = max((cy + r) / near, (cy + r) / (cz + r))
    u0 = max(int(math.floor(lo_x * f + width / 2.0)) - 1, 0)
    u1 = min(int(math.ceil(hi_x * f + width / 2.0)) + 1, width)
    v0 = max(int(math.floor(lo_y * f + height / 2.0)) - 1, 0)
    v1 = min(int(math.ceil(hi_y * f + height / 2.0)) + 1, height)
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def render_scene(spec: SceneSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast a scene: (depth_mm, amplitude, valid), each (H, W); amplitude = (rho cos(theta) + lobe) / r_m^2."""
    height, width = spec.height, spec.width
    f = focal_length_px(width, spec.hfov_deg)
    x, y = pixel_rays(height, width, spec.hfov_deg)
    depth = np.full((height, width), np.inf, dtype=np.float32)
    owner = np.full((height, width), -1, dtype=np.int16)
    normals = np.zeros((3, height, width), dtype=np.float32)
    for k, prim in enumerate(spec.primitives):
        bounds = prim.bounds()
        window = (
            (0, height, 0, width) if bounds is None else _screen_window(bounds, f, height, width, spec.min_depth_mm)
        )
        if window is None:
            continue
        v0, v1, u0, u1 = window
        xs, ys = x[v0:v1, u0:u1], y[v0:v1, u0:u1]
        t, nx, ny, nz = prim.intersect(xs, ys)
        closer = t < depth[v0:v1, u0:u1]
        depth[v0:v1, u0:u1] = np.where(closer, t, depth[v0:v1, u0:u1])
        owner[v0:v1, u0:u1] = np.where(closer, k, owner[v0:v1, u0:u1])
        for c, n in enumerate((nx, ny, nz)):
            normals[c, v0:v1, u0:u1] = np.where(closer, n, normals[c, v0:v1, u0:u1])
    # shading: cos(incidence) = |n . d| / (|n| |d|); range r = z |d|
    d_norm = np.sqrt(x * x + y * y + 1.0)
    n_norm = np.sqrt((normals**2).sum(axis=0)) + 1e-12
    cos_inc = np.abs(normals[0] * x + normals[1] * y + normals[2]) / (n_norm * d_norm)
    finite = np.isfinite(depth)
    px, py, pz = np.where(finite, depth * x, 0), np.where(finite, depth * y, 0), np.where(finite, depth, 0)
    returned = np.zeros((height, width), dtype=np.float32)  # rho cos(theta) + specular lobe
    for k, prim in enumerate(spec.primitives):
        sel = owner == k
        if sel.any():
            returned[sel] = prim.texture.albedo(px[sel], py[sel], pz[sel]) * cos_inc[sel] + prim.texture.lobe(
                cos_inc[sel]
            )
    range_m = np.where(finite, depth * d_norm, 1.0) / 1000.0
    amplitude = (returned / (range_m * range_m)).astype(np.float32)
    valid = depth_validity(depth, spec.min_depth_mm * 0.999, spec.max_depth_mm * 1.001)
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    amplitude = np.where(valid, amplitude, 0.0).astype(np.float32)
    return depth, amplitude, valid


@register_source("procedural")
class ProceduralSource:
    """Deterministic built-in scenes (no download): ids ``scene_000000`` ... ``scene_{n-1}``."""

    name = "procedural"
    # the amplitude is radiometric, (rho cos(theta) + lobe) / r_m^2: the physical signal route applies
    radiometric_amplitude = True

    def __init__(
        self,
        num_samples: int = 48,
        height: int = 480,
        width: int = 640,
        seed: int = 0,
        min_depth_mm: float = DEFAULT_MIN_DEPTH_MM,
        max_depth_mm: float = 2000.0,
        hfov_deg: float = DEFAULT_HFOV_DEG,
    ):
        if num_samples < 1:
            raise ValueError(
                f"data.source_kwargs.num_samples must be >= 1 for the procedural source, got {num_samples}"
            )
        if height < 8 or width < 8:
            raise ValueError(f"data.source_kwargs.height/width must be >= 8, got {height}x{width}")
        self.num_samples = int(num_samples)
        self.height, self.width = int(height), int(width)
        self.seed = int(seed)
        self.min_depth_mm, self.max_depth_mm = float(min_depth_mm), float(max_depth_mm)
        self.hfov_deg = float(hfov_deg)
        generate_scene(self.seed, 0, 8, 8, self.min_depth_mm, self.max_depth_mm)  # validates the depth range

    def supersampled(self, factor: int) -> ProceduralSource:
        """The same scenes ray-cast at ``factor`` times the resolution (scene geometry depends on the field of view
        and the aspect ratio only, so scene i is the same scene): what mixed pixels are averaged from."""
        return ProceduralSource(
            num_samples=self.num_samples,
            height=self.height * factor,
            width=self.width * factor,
            seed=self.seed,
            min_depth_mm=self.min_depth_mm,
            max_depth_mm=self.max_depth_mm,
            hfov_deg=self.hfov_deg,
        )

    @classmethod
    def config_keys(cls) -> list[str]:
        """``data.source_kwargs``: the ``__init__`` arguments but ``seed`` (``data.seed``), and
        ``max_depth_fraction``."""
        return [*init_keywords(cls, leave_out=("seed",)), "max_depth_fraction"]

    @classmethod
    def from_config(cls, settings: dict[str, Any], context: SourceContext) -> ProceduralSource:
        """Scenes of seed ``data.seed``; ``max_depth_mm`` unset (or null) = ``max_depth_fraction`` (default
        ``DEFAULT_MAX_DEPTH_FRACTION``) x the unambiguous range of the calibration (no scene wraps in phase)."""
        settings = dict(settings)
        fraction = settings.pop("max_depth_fraction", DEFAULT_MAX_DEPTH_FRACTION)
        if not 0 < float(fraction) <= 1:
            raise ValueError(f"data.source_kwargs.max_depth_fraction must be in (0, 1], got {fraction}")
        if settings.get("max_depth_mm") is None:
            settings["max_depth_mm"] = float(fraction) * float(context.calibration.unambiguous_range_mm)
        return cls(**settings, seed=context.seed)

    def sample_ids(self) -> list[str]:
        return [f"scene_{i:06d}" for i in range(self.num_samples)]

    def check(self) -> None:
        return None

    def index_of(self, sample_id: str) -> int:
        try:
            return int(sample_id.rsplit("_", 1)[1])
        except (IndexError, ValueError) as exc:
            raise KeyError(f"not a procedural sample id: {sample_id!r}") from exc

    def load(self, sample_id: str) -> RawSample:
        spec = generate_scene(
            self.seed,
            self.index_of(sample_id),
            self.height,
            self.width,
            self.min_depth_mm,
            self.max_depth_mm,
            self.hfov_deg,
        )
        depth, amplitude, valid = render_scene(spec)
        return RawSample(sample_id, depth, amplitude, valid)

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            "height": self.height,
            "width": self.width,
            "seed": self.seed,
            "min_depth_mm": self.min_depth_mm,
            "max_depth_mm": self.max_depth_mm,
            "hfov_deg": self.hfov_deg,
            "renderer": 2,
        }
