"""The procedural scene: a textured room (floor, walls, ceiling) with textured objects standing on the floor.

World frame follows the COLMAP habit for upright captures: y points DOWN (gravity), so "up" is -y.
The floor is the plane y = 0; the scene centre is the origin.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

from .config import SynthSceneConfig
from .geometry import Box, Cylinder, Plane, Primitive, Sphere
from .textures import Texture

WORLD_UP = np.array([0.0, -1.0, 0.0])


@dataclass(eq=False)
class Scene:
    """Primitives plus lighting. `light_dir` points FROM surfaces TOWARDS the light (unit)."""

    primitives: list[Primitive]
    light_dir: np.ndarray  # [3]
    ambient: float
    shadows: bool


def seed_streams(seed: int, n: int = 3) -> list[np.random.Generator]:
    """Independent generators (scene, cameras, points): changing e.g. num_points leaves the layout unchanged."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]


def rot_y(angle: float) -> np.ndarray:
    """Rotation about the vertical axis. -> [3, 3]"""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (QR of a Gaussian matrix, sign-fixed). -> [3, 3]"""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))[None]
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _color_pair(rng: np.random.Generator) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Two clearly contrasting albedos (different hue and value) so every pattern has strong edges."""
    h = rng.uniform()
    light = colorsys.hsv_to_rgb(h, rng.uniform(0.1, 0.55), rng.uniform(0.7, 0.95))
    dark = colorsys.hsv_to_rgb((h + rng.uniform(0.3, 0.7)) % 1.0, rng.uniform(0.2, 0.7), rng.uniform(0.15, 0.45))
    if rng.uniform() < 0.5:
        return light, dark
    return dark, light


def _texture(rng: np.random.Generator, kinds: tuple[str, ...], scales: dict[str, tuple[float, float]]) -> Texture:
    """Random texture among `kinds`; `scales` gives the (min, max) period per kind, tuned to stay >~2 px."""
    kind = kinds[int(rng.integers(len(kinds)))]
    a, b = _color_pair(rng)
    if kind == "text":  # text reads as dark ink on light paper
        a, b = (max(a, b, key=sum), min(a, b, key=sum))
    lo, hi = scales[kind]
    return Texture(
        kind=kind,
        color_a=tuple(float(x) for x in a),
        color_b=tuple(float(x) for x in b),
        scale=float(rng.uniform(lo, hi)),
        seed=int(rng.integers(2**31)),
        angle=float(rng.uniform(0, np.pi)) if kind in ("stripes", "checker", "text") else 0.0,
        detail=float(rng.uniform(0.15, 0.35)),
    )


# Periods in world units. Walls are ~7-11 units from the cameras, objects ~3-5: at the default 200 px /
# 60 deg (f ~ 173 px) a period p at distance z spans 173 * p / z px; text glyph pixels are 1/10 of a line.
_WALL_SCALES = {
    "checker": (0.7, 1.1),
    "stripes": (0.6, 1.0),
    "grid": (0.8, 1.4),
    "bricks": (0.8, 1.3),
    "noise": (1.2, 2.0),
    "text": (1.2, 1.6),
}
_FLOOR_SCALES = {"checker": (0.4, 0.6), "grid": (0.5, 0.8), "bricks": (0.6, 0.9)}
_OBJECT_SCALES = {
    "checker": (0.15, 0.3),
    "stripes": (0.15, 0.3),
    "grid": (0.2, 0.35),
    "bricks": (0.25, 0.4),
    "noise": (0.4, 0.7),
    "text": (0.4, 0.55),
}


def _room(cfg: SynthSceneConfig, rng: np.random.Generator) -> list[Plane]:
    """Floor (y=0), four walls and ceiling, all facing inwards; every ray from inside hits one of them."""
    r, h = cfg.room_half_size, cfg.room_height
    ex, ey, ez = np.eye(3)
    faces = [  # (point, inward normal, u axis, v axis)
        (np.zeros(3), -ey, ex, ez),  # floor
        (np.array([0.0, -h, 0.0]), ey, ex, ez),  # ceiling
        (np.array([r, 0.0, 0.0]), -ex, ez, ey),
        (np.array([-r, 0.0, 0.0]), ex, ez, ey),
        (np.array([0.0, 0.0, r]), -ez, ex, ey),
        (np.array([0.0, 0.0, -r]), ez, ex, ey),
    ]
    planes = []
    for i, (p, n, u, v) in enumerate(faces):
        if i == 0:
            tex = _texture(rng, tuple(_FLOOR_SCALES), _FLOOR_SCALES)
        else:
            tex = _texture(rng, tuple(_WALL_SCALES), _WALL_SCALES)
        planes.append(Plane(point=p, normal=n, u_axis=u, v_axis=v, texture=tex))
    return planes


def _objects(cfg: SynthSceneConfig, rng: np.random.Generator) -> list[Primitive]:
    """Non-overlapping objects resting on the floor inside the placement disc (rejection sampling)."""
    objs: list[Primitive] = []
    placed: list[tuple[np.ndarray, float]] = []  # (xz centre, footprint radius)
    kinds = tuple(_OBJECT_SCALES)
    for _ in range(cfg.num_objects):
        shape = ("sphere", "box", "cylinder")[int(rng.integers(3))]
        size = float(rng.uniform(cfg.object_min_size, cfg.object_max_size))
        tex = _texture(rng, kinds, _OBJECT_SCALES)
        if shape == "box":
            half = np.array([size, size * rng.uniform(0.6, 1.8), size * rng.uniform(0.5, 1.0)])
            footprint = float(np.hypot(half[0], half[2]))
        elif shape == "cylinder":
            half_h = size * rng.uniform(0.8, 2.2)
            footprint = size
        else:
            footprint = size
        yaw = float(rng.uniform(0, 2 * np.pi))
        for _attempt in range(200):
            rad = cfg.placement_radius * np.sqrt(rng.uniform())
            phi = rng.uniform(0, 2 * np.pi)
            xz = np.array([rad * np.cos(phi), rad * np.sin(phi)])
            if all(np.linalg.norm(xz - c) > footprint + f + 0.08 for c, f in placed):
                break
        else:
            continue  # crowded: skip this object rather than overlap
        placed.append((xz, footprint))
        if shape == "sphere":
            centre = np.array([xz[0], -size, xz[1]])  # up is -y: resting on the floor
            objs.append(Sphere(center=centre, radius=size, rotation=random_rotation(rng), texture=tex))
        elif shape == "box":
            centre = np.array([xz[0], -half[1], xz[1]])
            objs.append(Box(center=centre, half_extents=half, rotation=rot_y(yaw), texture=tex))
        else:
            centre = np.array([xz[0], -half_h, xz[1]])
            objs.append(
                Cylinder(center=centre, radius=size, half_height=float(half_h), rotation=rot_y(yaw), texture=tex)
            )
    return objs


def build_scene(cfg: SynthSceneConfig) -> Scene:
    """Deterministic scene from cfg.seed (uses only the 'scene' random stream)."""
    rng = seed_streams(cfg.seed)[0]
    prims: list[Primitive] = [*_room(cfg, rng), *_objects(cfg, rng)]
    az, el = np.deg2rad(cfg.light_azimuth_deg), np.deg2rad(cfg.light_elevation_deg)
    light = np.array([np.cos(el) * np.cos(az), 0.0, np.cos(el) * np.sin(az)]) + np.sin(el) * WORLD_UP
    return Scene(primitives=prims, light_dir=light / np.linalg.norm(light), ambient=cfg.ambient, shadows=cfg.shadows)
