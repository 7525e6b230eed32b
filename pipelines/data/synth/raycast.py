"""Exact, vectorised ray casting against the scene's analytic primitives.

Everything in a synthetic scene is the ground plane z = 0 or an upright primitive: a box
rotated about z, a vertical cylinder, a sphere. One origin casts R rays; each primitive type
is intersected for all rays at once ([R, P] arrays), so a camera or a LiDAR sweep is a
handful of numpy passes. Written here because no maintained library ray-casts analytic
primitives in numpy; a mesh ray tracer would need tessellation and a BVH for no gain.

Legend: R rays, B boxes, C cylinders, S spheres, P = B + C + S primitives (in that order).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SKY = -1
GROUND = -2
_EPS = 1e-4


@dataclass
class Primitives:
    """Upright primitives in the world frame and their per-primitive attributes."""

    box_center_B3: np.ndarray
    box_half_B3: np.ndarray
    box_yaw_B: np.ndarray
    cyl_base_C3: np.ndarray
    """(x, y, z0) of the bottom cap's centre."""
    cyl_height_C: np.ndarray
    cyl_radius_C: np.ndarray
    sph_center_S3: np.ndarray
    sph_radius_S: np.ndarray
    material_P: np.ndarray
    colour_P3: np.ndarray
    actor_P: np.ndarray
    """Index of the agent a primitive belongs to, -1 for static scenery."""

    @property
    def counts(self) -> tuple[int, int, int]:
        return len(self.box_yaw_B), len(self.cyl_height_C), len(self.sph_radius_S)

    def bounding_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """([P, 3] centres, [P] radii) enclosing each primitive, for culling."""
        cyl_c = self.cyl_base_C3.copy()
        cyl_c[:, 2] += self.cyl_height_C / 2
        centres = np.concatenate([self.box_center_B3, cyl_c, self.sph_center_S3]).reshape(-1, 3)
        radii = np.concatenate(
            [
                np.linalg.norm(self.box_half_B3, axis=1),
                np.hypot(self.cyl_radius_C, self.cyl_height_C / 2),
                self.sph_radius_S,
            ]
        )
        return centres, radii

    def subset(self, keep_P: np.ndarray) -> tuple[Primitives, np.ndarray]:
        """The kept primitives and their indices in ``self``."""
        b, c, _ = self.counts
        idx = np.flatnonzero(keep_P)
        kb, kc, ks = idx[idx < b], idx[(idx >= b) & (idx < b + c)] - b, idx[idx >= b + c] - b - c
        sub = Primitives(
            self.box_center_B3[kb],
            self.box_half_B3[kb],
            self.box_yaw_B[kb],
            self.cyl_base_C3[kc],
            self.cyl_height_C[kc],
            self.cyl_radius_C[kc],
            self.sph_center_S3[ks],
            self.sph_radius_S[ks],
            self.material_P[idx],
            self.colour_P3[idx],
            self.actor_P[idx],
        )
        return sub, idx


@dataclass
class PrimitiveBuilder:
    """Collects primitives one by one, then packs them into ``Primitives``."""

    boxes: list = field(default_factory=list)
    cyls: list = field(default_factory=list)
    sphs: list = field(default_factory=list)

    def box(self, center, half, yaw: float, material: int, colour, actor: int = -1) -> None:
        self.boxes.append((*center, *half, yaw, material, *colour, actor))

    def cylinder(self, base, height: float, radius: float, material: int, colour, actor: int = -1) -> None:
        self.cyls.append((*base, height, radius, material, *colour, actor))

    def sphere(self, center, radius: float, material: int, colour, actor: int = -1) -> None:
        self.sphs.append((*center, radius, material, *colour, actor))

    def extend(self, other: PrimitiveBuilder) -> None:
        self.boxes += other.boxes
        self.cyls += other.cyls
        self.sphs += other.sphs

    def build(self) -> Primitives:
        b = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 12)
        c = np.asarray(self.cyls, dtype=np.float64).reshape(-1, 10)
        s = np.asarray(self.sphs, dtype=np.float64).reshape(-1, 9)
        attrs = np.concatenate([b[:, 7:12], c[:, 5:10], s[:, 4:9]])
        return Primitives(
            b[:, 0:3],
            b[:, 3:6],
            b[:, 6],
            c[:, 0:3],
            c[:, 3],
            c[:, 4],
            s[:, 0:3],
            s[:, 3],
            attrs[:, 0].astype(np.int16),
            attrs[:, 1:4].astype(np.float32),
            attrs[:, 4].astype(np.int32),
        )


@dataclass
class Hits:
    """Nearest hit per ray."""

    t_R: np.ndarray
    """Ray parameter (distance along the unit direction); inf where nothing was hit."""
    prim_R: np.ndarray
    """Primitive index into the caster's ``Primitives``, ``GROUND`` or ``SKY``."""
    point_R3: np.ndarray
    """World hit point (undefined for sky)."""
    normal_R3: np.ndarray
    """World unit normal (undefined for sky)."""
    local_R3: np.ndarray
    """Hit point in the primitive's frame (box/sphere centre, cylinder base; box axes), for texturing."""
    coverage_RA: np.ndarray | None = None
    """Per ray and agent: does the ray hit the agent at all, occluded or not (when requested)."""


def _box_hits(o_3, d_R3, prims: Primitives) -> tuple[np.ndarray, np.ndarray]:
    """([R, B] entry distance, [R, B] hit mask) by the slab method in each box's frame."""
    cs, sn = np.cos(prims.box_yaw_B).astype(np.float32), np.sin(prims.box_yaw_B).astype(np.float32)
    rel = (o_3[None, :] - prims.box_center_B3).astype(np.float32)
    ol = np.stack([rel[:, 0] * cs + rel[:, 1] * sn, -rel[:, 0] * sn + rel[:, 1] * cs, rel[:, 2]], 1)
    h = prims.box_half_B3.astype(np.float32)
    dx, dy, dz = d_R3[:, 0:1], d_R3[:, 1:2], d_R3[:, 2:3]
    near = far = None
    # The z slab is shared by all boxes (upright), so it stays [R, 1] until broadcast.
    for axis, dl in enumerate((dx * cs + dy * sn, -dx * sn + dy * cs, dz)):
        inv = 1.0 / dl  # +-inf for rays parallel to a slab is what the slab test wants
        t1 = (-h[:, axis] - ol[:, axis]) * inv
        t2 = (h[:, axis] - ol[:, axis]) * inv
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        near = lo if near is None else np.maximum(near, lo)
        far = hi if far is None else np.minimum(far, hi)
    return near, (near <= far) & (near > _EPS)


def _cyl_hits(o_3, d_R3, prims: Primitives) -> tuple[np.ndarray, np.ndarray]:
    """([R, C] distance, [R, C] hit mask): the side wall, or the top cap seen from above."""
    base = prims.cyl_base_C3
    rel = (o_3[None, :2] - base[:, :2]).astype(np.float32)
    r = prims.cyl_radius_C.astype(np.float32)
    z0 = (base[:, 2] - o_3[2]).astype(np.float32)
    z1 = z0 + prims.cyl_height_C.astype(np.float32)
    dx, dy, dz = d_R3[:, 0:1], d_R3[:, 1:2], d_R3[:, 2:3]
    a = np.maximum(dx * dx + dy * dy, np.float32(1e-12))
    b = dx * rel[:, 0] + dy * rel[:, 1]
    c = (rel * rel).sum(1) - r * r
    disc = b * b - a * c
    t_side = (-b - np.sqrt(np.maximum(disc, 0))) / a
    z_side = t_side * dz
    side = (disc >= 0) & (t_side > _EPS) & (z_side >= z0) & (z_side <= z1)
    # The top cap is visible only from above it (the origin is outside every cylinder).
    t_top = z1 / np.where(np.abs(dz) < 1e-12, np.float32(-1e-12), dz)
    px, py = rel[:, 0] + t_top * dx, rel[:, 1] + t_top * dy
    top = (z1 < 0) & (t_top > _EPS) & (px * px + py * py <= r * r)
    t = np.where(side, t_side, np.where(top, t_top, np.inf)).astype(np.float32)
    return t, side | top


def _sph_hits(o_3, d_R3, prims: Primitives) -> tuple[np.ndarray, np.ndarray]:
    rel = (o_3[None, :] - prims.sph_center_S3).astype(np.float32)
    r = prims.sph_radius_S.astype(np.float32)
    # Elementwise rather than a BLAS product: bit-identical whatever the thread count.
    b = d_R3[:, 0:1] * rel[:, 0] + d_R3[:, 1:2] * rel[:, 1] + d_R3[:, 2:3] * rel[:, 2]
    c = (rel * rel).sum(1) - r * r
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0))
    return t, (disc >= 0) & (t > _EPS)


RAY_CHUNK = 1 << 15
"""Rays per pass: bounds the [R, P] temporaries (~4 MB each at 32 primitives) for large images."""


def cast(
    origin_3: np.ndarray,
    dirs_R3: np.ndarray,
    prims: Primitives,
    max_t: float,
    num_actors: int = 0,
) -> Hits:
    """Nearest hit of every ray from ``origin_3`` along unit ``dirs_R3`` (world frame).

    Hits farther than ``max_t`` count as sky. With ``num_actors`` > 0 the result also says,
    per ray and agent, whether the ray meets the agent ignoring occlusion (for visibility).
    """
    if len(dirs_R3) <= RAY_CHUNK:
        return _cast(origin_3, dirs_R3, prims, max_t, num_actors)
    parts = [
        _cast(origin_3, dirs_R3[i : i + RAY_CHUNK], prims, max_t, num_actors) for i in range(0, len(dirs_R3), RAY_CHUNK)
    ]
    cov = None if num_actors == 0 else np.concatenate([h.coverage_RA for h in parts])
    return Hits(
        *(
            np.concatenate([getattr(h, f) for h in parts])
            for f in ("t_R", "prim_R", "point_R3", "normal_R3", "local_R3")
        ),
        coverage_RA=cov,
    )


def _cast(origin_3: np.ndarray, dirs_R3: np.ndarray, prims: Primitives, max_t: float, num_actors: int) -> Hits:
    o = np.asarray(origin_3, dtype=np.float64)
    d = np.ascontiguousarray(dirs_R3, dtype=np.float32)
    n_rays = len(d)
    nb, nc, ns = prims.counts
    best_t = np.full(n_rays, np.inf, dtype=np.float32)
    best_p = np.full(n_rays, SKY, dtype=np.int64)
    coverage = np.zeros((n_rays, num_actors), dtype=bool) if num_actors else None

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # Ground plane.
        t_g = np.where(d[:, 2] < -1e-9, -np.float32(o[2]) / d[:, 2], np.inf).astype(np.float32)
        ground = t_g <= max_t
        best_t = np.where(ground, t_g, best_t)
        best_p = np.where(ground, GROUND, best_p)
        offset = 0
        for count, fn in ((nb, _box_hits), (nc, _cyl_hits), (ns, _sph_hits)):
            if count:
                t_RK, hit_RK = fn(o, d, prims)
                t_RK = np.where(hit_RK, t_RK, np.inf)
                k = np.argmin(t_RK, axis=1)
                t_min = t_RK[np.arange(n_rays), k]
                closer = t_min < best_t
                best_t = np.where(closer, t_min, best_t)
                best_p = np.where(closer, k + offset, best_p)
                if coverage is not None:
                    actors = prims.actor_P[offset : offset + count]
                    onehot_KA = (actors[:, None] == np.arange(num_actors)[None, :]).astype(np.float32)
                    coverage |= (hit_RK.astype(np.float32) @ onehot_KA) > 0
            offset += count
    best_p = np.where(best_t > max_t, SKY, best_p)
    best_t = np.where(best_p == SKY, np.inf, best_t)
    point = o[None, :] + np.where(np.isfinite(best_t), best_t, 0.0)[:, None].astype(np.float64) * d
    normal, local = _surface(point, best_p, prims)
    return Hits(best_t, best_p, point, normal, local, coverage)


def _surface(point_R3: np.ndarray, prim_R: np.ndarray, prims: Primitives) -> tuple[np.ndarray, np.ndarray]:
    """World normals and primitive-local hit coordinates of the winning primitives."""
    nb, nc, _ = prims.counts
    normal = np.zeros_like(point_R3)
    normal[:, 2] = 1.0  # ground and sky
    local = point_R3.copy()
    is_box = (prim_R >= 0) & (prim_R < nb)
    if is_box.any():
        k = prim_R[is_box]
        cs, sn = np.cos(prims.box_yaw_B[k]), np.sin(prims.box_yaw_B[k])
        rel = point_R3[is_box] - prims.box_center_B3[k]
        lx, ly = rel[:, 0] * cs + rel[:, 1] * sn, -rel[:, 0] * sn + rel[:, 1] * cs
        lp = np.stack([lx, ly, rel[:, 2]], 1)
        q = np.abs(lp) / prims.box_half_B3[k]
        axis = np.argmax(q, axis=1)
        sign = np.sign(lp[np.arange(len(k)), axis])
        nl = np.zeros_like(lp)
        nl[np.arange(len(k)), axis] = sign
        normal[is_box] = np.stack([nl[:, 0] * cs - nl[:, 1] * sn, nl[:, 0] * sn + nl[:, 1] * cs, nl[:, 2]], 1)
        local[is_box] = lp
    is_cyl = (prim_R >= nb) & (prim_R < nb + nc)
    if is_cyl.any():
        k = prim_R[is_cyl] - nb
        rel = point_R3[is_cyl] - prims.cyl_base_C3[k]
        top = rel[:, 2] >= prims.cyl_height_C[k] - 1e-3
        radial = np.concatenate([rel[:, :2], np.zeros((len(k), 1))], 1)
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
        normal[is_cyl] = np.where(top[:, None], [0.0, 0.0, 1.0], radial)
        local[is_cyl] = rel
    is_sph = prim_R >= nb + nc
    if is_sph.any():
        k = prim_R[is_sph] - nb - nc
        rel = point_R3[is_sph] - prims.sph_center_S3[k]
        normal[is_sph] = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-9)
        local[is_sph] = rel
    return normal, local


def cull(
    prims: Primitives, origin_3: np.ndarray, max_t: float, planes_K3: np.ndarray | None = None
) -> tuple[Primitives, np.ndarray]:
    """Primitives whose bounding sphere lies within ``max_t`` of the origin and inside every plane.

    ``planes_K3`` are inward unit normals of planes through the origin (a frustum or a wedge);
    a sphere is kept unless it lies entirely on the outer side of one of them.
    """
    centres, radii = prims.bounding_spheres()
    v = centres - np.asarray(origin_3)[None, :]
    keep = np.linalg.norm(v, axis=1) - radii <= max_t
    if planes_K3 is not None and len(planes_K3):
        keep &= (v @ np.asarray(planes_K3).T >= -radii[:, None]).all(axis=1)
    return prims.subset(keep)
