"""One scene of a benchmark suite (:class:`SceneEntry`): where its images come from, the scene folder a method
trains on, and what of it enters a run's fingerprint."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Optional

from gsmsdr_ns.bench.method_base import MethodSpec
from gsmsdr_ns.bench.real_scenes import RealSceneSpec
from gsmsdr_ns.bench.scenes import SceneSpec


@dataclass(frozen=True)
class SceneEntry:
    """One scene of a suite: generated (``spec``), built from real photos (``real``) or the user's own (``path``,
    optional ``sharp_path``)."""

    name: str
    """Scene name in the tables and run ids."""
    spec: Optional[SceneSpec] = None
    """The generated scene, or None for a user scene."""
    path: Optional[Path] = None
    """A user scene's folder."""
    sharp_path: Optional[Path] = None
    """A user scene's sharp twin (for the ``sharp`` upper bound)."""
    real: Optional[RealSceneSpec] = None
    """A scene built from real photos (``gsmsdr_ns.bench.real_scenes``), or None."""
    random_init: bool = False
    """Start the Gaussians from random points instead of the scene's sparse points (suite key ``init: random``):
    a capture without structure-from-motion points."""

    @property
    def generated(self) -> bool:
        return self.spec is not None or self.real is not None

    def supports(self, method: MethodSpec) -> bool:
        """False for the sharp upper bound on a user scene without ``sharp_path``."""
        return not method.sharp_data or self.generated or self.sharp_path is not None

    @staticmethod
    def _records(method: MethodSpec) -> str:
        """Which twin of a real-photo scene ``method`` trains on: "true" (the true records) or "estimated" (no
        records: the dataparser estimates them)."""
        return "true" if method.true_records and not method.sharp_data else "estimated"

    def trains_on_estimated_records(self, method: MethodSpec) -> bool:
        """Whether ``method``'s model reads records the dataparser estimates (a blur model on a real-photo scene's
        twin without records)."""
        return self.real is not None and method.has_blur_field and self._records(method) == "estimated"

    def _real_folder(self, method: MethodSpec) -> tuple[RealSceneSpec, str, str]:
        """(spec, records, photos) of the real-photo scene ``method`` trains on (:func:`ensure_real_scene`'s
        arguments). A preset that degrades nothing leaves the sharp photos as they are, so its "sharp photos posed
        by the degraded photos" are its own scene: the same folder serves both."""
        from gsmsdr_ns.bench.real_scenes import degrade_config

        assert self.real is not None
        if method.sharp_data and method.degraded_poses:
            photos = "sharp" if degrade_config(self.real).resolved_effects() else "degraded"
            return self.real, "estimated", photos
        real = self.real.sharp_twin() if method.sharp_data else self.real
        return real, self._records(method), "degraded"

    def data(self, method: MethodSpec, scene_root: Path, log: Optional[Callable[[str], None]] = None) -> Path:
        """The scene folder ``method`` trains on (generated on first use, under ``scene_root/scenes``)."""
        if self.spec is not None:
            from gsmsdr_ns.bench.scenes import ensure_scene

            spec = self.spec.with_variant("sharp") if method.sharp_data else self.spec
            return ensure_scene(scene_root, spec, log)
        if self.real is not None:
            from gsmsdr_ns.bench.real_scenes import ensure_real_scene

            real, records, photos = self._real_folder(method)
            return ensure_real_scene(scene_root, real, records, log=log, photos=photos)
        path = self.sharp_path if method.sharp_data else self.path
        assert path is not None
        return path

    def data_key(self, method: MethodSpec) -> Dict[str, Any]:
        """What names the folder :meth:`data` gives ``method``, without building it, and how training starts from
        it: two runs whose keys are equal read the same images, poses and records and start alike (whatever their
        scene is called)."""
        key = self.folder_key(method)
        return {**key, "init": "random"} if self.random_init else key

    def folder_key(self, method: MethodSpec) -> Dict[str, Any]:
        """What names the folder :meth:`data` gives ``method``, without building it."""
        if self.spec is not None:
            spec = self.spec.with_variant("sharp") if method.sharp_data else self.spec
            return {"generated": dataclasses.asdict(spec)}
        if self.real is not None:
            real, records, photos = self._real_folder(method)
            return {**self._fingerprint(), "real": dataclasses.asdict(real), "records": records, "photos": photos}
        path = self.sharp_path if method.sharp_data else self.path
        assert path is not None
        return {"path": str(Path(path).resolve())}

    def configure(self, config) -> None:
        """Scene-specific settings on a method's TrainerConfig (a real scene's downscaled copies, random init)."""
        if self.real is not None:
            self.real.configure(config)
        if self.random_init:
            config.pipeline.model.random_init = True

    def describe(self) -> str:
        text = self._describe()
        return text + ", Gaussians started from random points (no sparse points)" if self.random_init else text

    def _describe(self) -> str:
        if self.spec is not None:
            s = self.spec
            return (f"generated `{s.variant}`, {s.width}x{s.height}, {s.num_views} views (every {s.hold}th a sharp "
                    f"test view), {s.num_points} points, scene seed {s.seed}")  # fmt: skip
        if self.real is not None:
            return self.real.describe()
        sharp = f", sharp twin `{self.sharp_path}`" if self.sharp_path is not None else ""
        return f"user scene `{self.path}`{sharp}"

    def fingerprint(self) -> Dict[str, Any]:
        """What the scene contributes to a record's fingerprint (``init`` only when random: older records keep
        theirs)."""
        key = self._fingerprint()
        return {**key, "init": "random"} if self.random_init else key

    def _fingerprint(self) -> Dict[str, Any]:
        if self.spec is not None:
            return {"generated": dataclasses.asdict(self.spec)}
        if self.real is not None:
            from gsmsdr_ns.bench.real_scenes import COMPOSED_LAYOUT_VERSION, REAL_SCENE_VERSION

            return {"real": dataclasses.asdict(self.real), "layout": COMPOSED_LAYOUT_VERSION,
                    "builder": REAL_SCENE_VERSION}  # fmt: skip
        return {"path": str(self.path), "sharp_path": None if self.sharp_path is None else str(self.sharp_path)}


__all__ = ["SceneEntry"]
