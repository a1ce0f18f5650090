"""Analytic primitives: ray intersection and surface attributes (normal, texture uv), vectorised in numpy.

Conventions: rays are o + t * d with d NOT necessarily unit length (primary rays use d with camera-z
component 1, so t is the z-depth). Misses are t = +inf. Only hits with t > T_EPS count.
Rotations are world_from_local 3x3 matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .textures import Texture

T_EPS = 1e-6


@dataclass(eq=False)
class Plane:
    """One-sided infinite plane; rays hit it only from the side its normal points to (room walls, floor)."""

    point: np.ndarray  # [3] a point on the plane
    normal: np.ndarray  # [3] unit normal, pointing to the visible side
    u_axis: np.ndarray  # [3] unit texture u direction (in the plane)
    v_axis: np.ndarray  # [3] unit texture v direction (in the plane)
    texture: Texture
    casts_shadow: bool = False  # room faces never block the (distant) light
    bounding_radius = None  # unbounded: no culling

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """o, d: [N, 3] -> t [N]."""
        denom = d @ self.normal
        num = (self.point - o) @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        return np.where((denom < -1e-12) & (t > T_EPS), t, np.inf)

    def surface(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """p: [N, 3] hit points -> (normal [N, 3], uv [N, 2])."""
        rel = p - self.point
        uv = np.stack([rel @ self.u_axis, rel @ self.v_axis], axis=-1)
        return np.broadcast_to(self.normal, p.shape).copy(), uv


def _triplanar_uv(local: np.ndarray, normal_local: np.ndarray) -> np.ndarray:
    """Cube-map style uv: the two local coords orthogonal to the dominant normal axis. [N,3],[N,3] -> [N,2]."""
    axis = np.argmax(np.abs(normal_local), axis=-1)
    sign = np.sign(np.take_along_axis(normal_local, axis[:, None], axis=-1))[:, 0]
    others = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    uv = np.take_along_axis(local, others, axis=-1)
    # Offset each face differently so opposite faces do not show identical noise.
    return uv + (axis * 2 + (sign > 0))[:, None] * np.array([3.7, 5.3])


@dataclass(eq=False)
class Sphere:
    """Sphere with a texture orientation (rotation) so patterns are not aligned to world axes."""

    center: np.ndarray  # [3]
    radius: float
    rotation: np.ndarray  # [3, 3] world_from_local (texture frame)
    texture: Texture
    casts_shadow: bool = True

    @property
    def bounding_radius(self) -> float:
        return self.radius

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """o, d: [N, 3] -> t [N] (nearest root in front of the origin)."""
        oc = o - self.center
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - self.radius**2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = (-b - sq) / a, (-b + sq) / a
        t = np.where(t0 > T_EPS, t0, np.where(t1 > T_EPS, t1, np.inf))
        return np.where(disc >= 0, t, np.inf)

    def surface(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = (p - self.center) / self.radius
        n_local = n @ self.rotation
        return n, _triplanar_uv(n_local * self.radius, n_local)


@dataclass(eq=False)
class Box:
    """Oriented box (slab test in its local frame)."""

    center: np.ndarray  # [3]
    half_extents: np.ndarray  # [3] local half sizes
    rotation: np.ndarray  # [3, 3] world_from_local
    texture: Texture
    casts_shadow: bool = True

    @property
    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.half_extents))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        lo = (o - self.center) @ self.rotation
        ld = d @ self.rotation
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / ld
            t1 = (-self.half_extents - lo) * inv
            t2 = (self.half_extents - lo) * inv
        lo_t, hi_t = np.fmin(t1, t2), np.fmax(t1, t2)  # fmin/fmax drop the NaN of 0*inf (ray in a slab face)
        tnear = np.fmax(np.fmax(lo_t[:, 0], lo_t[:, 1]), lo_t[:, 2])
        tfar = np.fmin(np.fmin(hi_t[:, 0], hi_t[:, 1]), hi_t[:, 2])
        hit = (tnear <= tfar) & (tnear > T_EPS)  # origins inside the box are not needed here
        return np.where(hit, tnear, np.inf)

    def surface(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = (p - self.center) @ self.rotation
        r = local / self.half_extents
        axis = np.argmax(np.abs(r), axis=-1)
        n_local = np.zeros_like(local)
        np.put_along_axis(n_local, axis[:, None], np.sign(np.take_along_axis(r, axis[:, None], -1)), -1)
        return n_local @ self.rotation.T, _triplanar_uv(local, n_local)


@dataclass(eq=False)
class Cylinder:
    """Capped cylinder along its local y axis."""

    center: np.ndarray  # [3]
    radius: float
    half_height: float
    rotation: np.ndarray  # [3, 3] world_from_local
    texture: Texture
    casts_shadow: bool = True

    @property
    def bounding_radius(self) -> float:
        return float(np.hypot(self.radius, self.half_height))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        lo = (o - self.center) @ self.rotation
        ld = d @ self.rotation
        a = ld[:, 0] ** 2 + ld[:, 2] ** 2
        b = lo[:, 0] * ld[:, 0] + lo[:, 2] * ld[:, 2]
        c = lo[:, 0] ** 2 + lo[:, 2] ** 2 - self.radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            y_side = lo[:, 1] + t_side * ld[:, 1]
            side_ok = (disc >= 0) & (a > 1e-15) & (t_side > T_EPS) & (np.abs(y_side) <= self.half_height)
            t = np.where(side_ok, t_side, np.inf)
            for cap in (-self.half_height, self.half_height):
                t_cap = (cap - lo[:, 1]) / ld[:, 1]
                x = lo[:, 0] + t_cap * ld[:, 0]
                z = lo[:, 2] + t_cap * ld[:, 2]
                cap_ok = (t_cap > T_EPS) & (x * x + z * z <= self.radius**2)
                t = np.where(cap_ok & (t_cap < t), t_cap, t)
        return t

    def surface(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = (p - self.center) @ self.rotation
        rho = np.hypot(local[:, 0], local[:, 2])
        on_cap = np.abs(local[:, 1]) / self.half_height > rho / self.radius
        n_local = np.where(
            on_cap[:, None],
            np.stack([np.zeros_like(rho), np.sign(local[:, 1]), np.zeros_like(rho)], -1),
            np.stack([local[:, 0], np.zeros_like(rho), local[:, 2]], -1) / np.maximum(rho, 1e-12)[:, None],
        )
        ang = np.arctan2(local[:, 2], local[:, 0])
        uv_side = np.stack([ang * self.radius, local[:, 1]], -1)
        uv_cap = local[:, [0, 2]] + np.where(local[:, 1:2] > 0, 11.0, 23.0)
        return n_local @ self.rotation.T, np.where(on_cap[:, None], uv_cap, uv_side)


Primitive = Plane | Sphere | Box | Cylinder
