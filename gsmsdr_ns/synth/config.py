"""Configuration of the procedural default scene (one dataclass, loadable from a YAML preset)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..io.config import load_dataclass, read_yaml_mapping


@dataclass
class SynthSceneConfig:
    """Everything that determines a generated scene; the same config always gives the same bytes."""

    seed: int = 0
    """Master seed; scene layout, cameras and sparse points use independent child streams of it."""
    num_views: int = 32
    """Number of camera views on the orbit (images are named in capture order)."""
    width: int = 200
    """Image width in pixels."""
    height: int = 150
    """Image height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view in degrees (square pixels, principal point at the image centre)."""
    supersample: int = 3
    """Anti-aliasing: supersample x supersample stratified rays per pixel, box-filtered."""
    orbit_radius: float = 4.0
    """Mean distance from the camera centre to the look-at target (world units)."""
    radius_jitter: float = 0.3
    """Uniform +- jitter on the orbit radius per view."""
    elevation_deg: float = 25.0
    """Mean camera elevation above the horizontal plane through the target."""
    elevation_amplitude_deg: float = 8.0
    """Elevation oscillates (two periods per orbit) so the camera centres are not coplanar."""
    elevation_jitter_deg: float = 3.0
    """Uniform +- random jitter on the elevation per view."""
    azimuth_jitter_deg: float = 3.0
    """Uniform +- random jitter on the (evenly spaced) azimuth per view."""
    target_height: float = 0.4
    """Height of the look-at target above the floor."""
    target_jitter: float = 0.1
    """Std of the Gaussian jitter of the per-view look-at target (world units)."""
    num_objects: int = 7
    """Number of textured primitives (spheres, boxes, cylinders) standing on the floor."""
    object_min_size: float = 0.25
    """Smallest object radius / horizontal half-extent."""
    object_max_size: float = 0.6
    """Largest object radius / horizontal half-extent."""
    placement_radius: float = 1.8
    """Object centres lie within this distance of the scene centre."""
    room_half_size: float = 7.0
    """Half width/depth of the enclosing room box (floor is its bottom face), so every pixel hits geometry."""
    room_height: float = 5.0
    """Height of the room (ceiling above the floor)."""
    light_azimuth_deg: float = 35.0
    """Azimuth of the directional light."""
    light_elevation_deg: float = 55.0
    """Elevation of the directional light above the horizon."""
    ambient: float = 0.35
    """Ambient term of the Lambertian shading (the rest is directional diffuse)."""
    shadows: bool = True
    """Cast hard shadows of the objects (the room walls never occlude the light)."""
    num_points: int = 3000
    """Number of sparse 3D points written to points3D.bin."""
    min_track_length: int = 2
    """Each sparse point must be visible (unoccluded, inside the image) in at least this many views."""
    image_prefix: str = "frame_"
    """Image file stem prefix; names are <prefix><index:05d>.png."""

    def __post_init__(self) -> None:
        # Fail early with a clear message instead of producing an odd scene.
        if self.num_views < 2:
            raise ValueError(f"num_views must be >= 2, got {self.num_views}")
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size too small: {self.width}x{self.height}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        if not 1.0 < self.fov_deg < 170.0:
            raise ValueError(f"fov_deg must be in (1, 170), got {self.fov_deg}")
        if self.num_objects < 0 or self.num_points < 0:
            raise ValueError("num_objects and num_points must be >= 0")
        if self.min_track_length < 2:
            raise ValueError("min_track_length must be >= 2")
        if not 0 < self.object_min_size <= self.object_max_size:
            raise ValueError("need 0 < object_min_size <= object_max_size")
        max_r = self.orbit_radius + self.radius_jitter
        if max_r + 0.5 > self.room_half_size:
            raise ValueError("orbit does not fit in the room: increase room_half_size or reduce orbit_radius")
        if self.radius_jitter >= self.orbit_radius:
            raise ValueError("radius_jitter must be smaller than orbit_radius")
        # Camera heights over the orbit must stay between floor and ceiling (world up is -y).
        spread = abs(self.elevation_amplitude_deg) + abs(self.elevation_jitter_deg)
        el_hi = math.radians(min(self.elevation_deg + spread, 80.0))
        el_lo = math.radians(max(self.elevation_deg - spread, -80.0))
        top = self.target_height + max_r * math.sin(el_hi)
        bottom = self.target_height + max_r * math.sin(el_lo)
        if top > self.room_height - 0.2 or bottom < 0.05:
            raise ValueError(
                f"camera heights [{bottom:.2f}, {top:.2f}] leave the room (floor 0, ceiling {self.room_height}); "
                "adjust elevation_deg / orbit_radius / room_height"
            )


def config_from_dict(
    values: Mapping[str, Any], base: SynthSceneConfig | None = None, source: str | Path | None = None
) -> SynthSceneConfig:
    """Overlay `values` on `base` (default config); unknown keys and wrong types are an InputError naming `source`
    and the key (typos must not pass silently)."""
    return load_dataclass(SynthSceneConfig, values, source, base if base is not None else SynthSceneConfig())


def load_preset(path: str | Path) -> SynthSceneConfig:
    """Read a YAML preset (flat mapping of SynthSceneConfig fields; missing fields keep their defaults)."""
    return config_from_dict(read_yaml_mapping(Path(path)), source=path)
