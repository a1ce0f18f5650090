"""Accuracy of the degradation estimate on scenes with known records (prints a table). Run from the repository
root::

    python -m tools.estimate.evaluate                      # generated scenes + the real fern photos
    python -m tools.estimate.evaluate --photos --size 400 300     # generated scenes only, larger

Scenes: procedural scenes written by ``gsmsdr-synth --variant <v>`` (images rendered, then degraded) and a set of
real sharp photos (LLFF fern, ``poses_bounds.npy`` + images) degraded by ``gsmsdr-degrade``'s pipeline with the
same built-in presets. Every scene is written once into ``--work`` and reused. Scores per scene:

* sharp vs degraded: share of images whose estimate (sharp, or anything else) matches the truth (``degraded``);
  an ``unknown`` estimate counts as degraded (the model then simulates every degradation);
* motion vs defocus: among images blurred by exactly one of the two, the share labelled with that one (an
  ``unknown`` kind of blur is not counted as right; "wrong blur kind" counts the images labelled with the other,
  "kind right when decided" is the share right among the images labelled motion or defocus);
* mixres factor: among images with a known factor > 1, the share whose estimated factor is within one group.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Tuple

import numpy as np
import tyro

from gsmsdr_ns.data.cameras import llff_to_opencv
from gsmsdr_ns.degrade.variants import BUILTIN_PRESETS, VARIANTS
from gsmsdr_ns.estimate.classify import EstimateConfig, estimate_degradations
from gsmsdr_ns.io.images import list_images, read_image
from gsmsdr_ns.io.photo_sets import find_photo_set, photo_set_roots

SYNTH_VARIANTS = ("sharp", "motion", "defocus", "mixres", "mixed", "motion-strong", "defocus-strong")
PHOTO_VARIANTS = ("motion", "defocus", "mixres", "motion-defocus", "mixed", "motion-strong", "defocus-strong")
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
FERN = find_photo_set("llff-fern", subfolder="images_8") or photo_set_roots()[0] / "llff-fern"
"""The real LLFF fern photos ($GSMSDR_DATA_DIR/llff-fern, else shared/data/llff-fern beside the repository)."""


def llff_transforms(images_dir: Path, poses_bounds: Path) -> dict:
    """nerfstudio transforms.json content for an LLFF folder (absolute image paths; hwf scaled to the images).

    LLFF rows hold [down, right, backwards | t | hwf] of the original capture; transforms use OpenGL
    [right, up, backwards] camera-to-world matrices.
    """
    names = list_images(images_dir)
    pb = np.load(poses_bounds)
    if len(pb) != len(names):
        raise ValueError(f"{poses_bounds} has {len(pb)} poses but {images_dir} holds {len(names)} images")
    poses = pb[:, :15].reshape(-1, 3, 5)
    h, w = read_image(images_dir / names[0]).shape[:2]
    scale = w / float(poses[0, 1, 4])
    c2w_gl = llff_to_opencv(poses) @ _OPENCV_TO_OPENGL
    frames = [{"file_path": str((images_dir / n).absolute()), "transform_matrix": m.tolist()} for n, m in
              zip(names, c2w_gl)]  # fmt: skip
    return {"camera_model": "PINHOLE", "w": w, "h": h, "fl_x": float(poses[0, 2, 4]) * scale,
            "fl_y": float(poses[0, 2, 4]) * scale, "cx": w / 2, "cy": h / 2, "frames": frames}  # fmt: skip


def photo_scene(work: Path, images_dir: Path, variant: str, seed: int = 0) -> Path:
    """Degrade the sharp photos of an LLFF folder with a built-in preset (written once, reused)."""
    from gsmsdr_ns.degrade.pipeline import degrade_scene

    out = work / f"photos-{images_dir.name}-{variant}"
    if (out / "degradation.json").is_file():
        return out
    src = work / f"photos-{images_dir.name}-source"
    if not (src / "transforms.json").is_file():
        src.mkdir(parents=True, exist_ok=True)
        doc = llff_transforms(images_dir, images_dir.parent / "poses_bounds.npy")
        (src / "transforms.json").write_text(json.dumps(doc, indent=1), encoding="utf8")
    preset = "motion-mild" if variant == "motion-defocus" else VARIANTS[variant]
    effects = ("motion", "defocus") if variant == "motion-defocus" else BUILTIN_PRESETS[preset].effects
    cfg = dataclasses.replace(BUILTIN_PRESETS[preset], effects=effects, seed=seed, workers=1)
    return degrade_scene(src, out, cfg, preset=preset)


def synth_scene(work: Path, variant: str, size: Tuple[int, int], views: int, seed: int = 0) -> Path:
    """A procedural scene degraded with the variant's preset (written once, reused)."""
    from gsmsdr_ns.degrade.variants import generate_variant
    from gsmsdr_ns.synth.config import SynthSceneConfig

    out = work / f"synth-{variant}-{size[0]}x{size[1]}-{views}"
    if (out / "degradation.json").is_file():
        return out
    cfg = SynthSceneConfig(seed=seed, num_views=views, width=size[0], height=size[1])
    return generate_variant(out, cfg, variant)


def truth_of(entry: dict) -> tuple[str, int]:
    """(label, mixres factor) of a degradation.json entry: sharp, motion, defocus, mixres or a '+' list."""
    effects = entry.get("effects", {})
    if not entry.get("degraded", bool(effects)):
        return "sharp", 1
    names = [e for e in ("motion", "defocus", "mixres") if e in effects]
    return "+".join(names) or "noise", int(effects.get("mixres", {}).get("factor", 1))


@dataclass
class SceneScore:
    """Counts of one scene."""

    name: str
    images: int = 0
    sharp_ok: int = 0
    blur_total: int = 0
    blur_ok: int = 0
    blur_wrong: int = 0
    mixres_total: int = 0
    mixres_ok: int = 0
    unknown: int = 0
    seconds: float = 0.0
    mistakes: list = field(default_factory=list)


def score_scene(scene: Path, name: str, config: EstimateConfig) -> SceneScore:
    """Estimate every image of scene/images and compare with scene/degradation.json."""
    doc = json.loads((scene / "degradation.json").read_text(encoding="utf8"))
    names = sorted(doc["images"])
    images = [read_image(scene / "images" / n) for n in names]
    t0 = time.perf_counter()
    estimates = estimate_degradations(images, config)
    score = SceneScore(name, len(names), seconds=time.perf_counter() - t0)
    for n, est in zip(names, estimates):
        label, factor = truth_of(doc["images"][n])
        degraded = label != "sharp"
        score.unknown += est.label == "unknown"
        ok = (est.label != "sharp") == degraded
        score.sharp_ok += ok
        if label in ("motion", "defocus"):
            score.blur_total += 1
            score.blur_ok += est.label == label
            score.blur_wrong += est.label in ("motion", "defocus") and est.label != label
            ok = ok and est.label == label
        if factor > 1:
            score.mixres_total += 1
            score.mixres_ok += est.mixres_factor is not None and abs(est.mixres_factor - factor) <= 1
        if not ok:
            score.mistakes.append(f"{n}: {label} -> {est.label} (sharpness {est.sharpness:.2f}, "
                                  f"anisotropy {est.anisotropy:.2f})")  # fmt: skip
    return score


def _pct(ok: int, total: int) -> str:
    return f"{100.0 * ok / total:5.1f}% ({ok}/{total})" if total else "-"


def total_of(scores: list[SceneScore], name: str) -> SceneScore:
    """The counts of several scenes added up (mistakes not kept)."""
    total = SceneScore(name)
    for s in scores:
        for key in ("images", "sharp_ok", "blur_total", "blur_ok", "blur_wrong", "mixres_total", "mixres_ok",
                    "unknown", "seconds"):  # fmt: skip
            setattr(total, key, getattr(total, key) + getattr(s, key))
    return total


def format_table(scores: list[SceneScore]) -> str:
    """Markdown table: one row per scene, a total row per kind of scene (the first word of the names: synth,
    photos) when there are several kinds, and a total row."""
    head = ("| scene | images | sharp vs degraded | motion vs defocus | wrong blur kind | kind right when decided | "
            "mixres factor +-1 | unknown | s/image |")  # fmt: skip
    rows = [head, "|" + "---|" * 9]
    kinds = list(dict.fromkeys(s.name.split()[0] for s in scores))
    totals = []
    if len(kinds) > 1:
        totals = [total_of([s for s in scores if s.name.split()[0] == k], f"**{k}**") for k in kinds]
    for s in scores + totals + [total_of(scores, "**all**")]:
        decided = s.blur_ok + s.blur_wrong
        rows.append(f"| {s.name} | {s.images} | {_pct(s.sharp_ok, s.images)} | {_pct(s.blur_ok, s.blur_total)} | "
                    f"{s.blur_wrong if s.blur_total else '-'} | {_pct(s.blur_ok, decided)} | "
                    f"{_pct(s.mixres_ok, s.mixres_total)} | {s.unknown} | "
                    f"{s.seconds / max(s.images, 1):.3f} |")  # fmt: skip
    return "\n".join(rows)


@dataclass
class EvaluateCLI:
    """Accuracy of gsmsdr's degradation estimate on degraded scenes with known records."""

    work: Path = Path("/tmp/gsmsdr-estimate-eval")
    """Where the evaluation scenes are written (once; later runs reuse them)."""
    photos: Tuple[Path, ...] = (FERN / "images_8",)
    """Folders of real sharp photos with poses_bounds.npy beside them (LLFF); none to skip."""
    synth: bool = True
    """Evaluate the procedural scenes (gsmsdr-synth variants)."""
    size: Tuple[int, int] = (200, 150)
    """Width and height of the procedural scenes."""
    views: int = 24
    """Views per procedural scene."""
    seed: int = 0
    """Seed of the scenes and their degradations."""
    verbose: bool = False
    """List every misjudged image."""
    config: EstimateConfig = field(default_factory=EstimateConfig)
    """Estimate settings."""

    def main(self) -> list[SceneScore]:
        scenes: list[tuple[str, Path]] = []
        if self.synth:
            for v in SYNTH_VARIANTS:
                scenes.append((f"synth {v}", synth_scene(self.work, v, self.size, self.views, self.seed)))
        for folder in self.photos:
            for v in PHOTO_VARIANTS:
                scenes.append((f"photos {folder.name} {v}", photo_scene(self.work, Path(folder), v, self.seed)))
        scores = [score_scene(path, name, self.config) for name, path in scenes]
        print(format_table(scores))
        if self.verbose:
            for s in scores:
                for m in s.mistakes:
                    print(f"{s.name}: {m}")
        return scores


if __name__ == "__main__":
    tyro.cli(EvaluateCLI).main()
