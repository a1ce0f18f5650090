"""The bench's one method registry: what each suite method (a table row) trains.

Every method is a preset of ``gsmsdr_ns.plugin.method_config`` (its *base*) with some ``BlurFieldConfig`` or
``DegradationConfig`` fields replaced:

* base ``plain``: the ``gsmsdr`` preset with ``degradation sharp``, i.e. plain splatfacto Gaussians fitted straight
  to the degraded training images (no blur field, no resolution model);
* base ``gsmsdr`` / ``gsmsdr-lite`` / ``gsmsdr-cpu``: those presets, ``degradation auto`` (per image from the scene's
  ``degradation.json``);
* base ``sharp``: ``plain`` trained on the *sharp* twin of the same scene (identical cameras and test views): the
  upper bound a perfect deblurring method could reach with the same budget.

Step-dependent schedules are not set here: the runner applies one :class:`gsmsdr_ns.plugin.schedule.TrainingSchedule`
to every method.
"""

from __future__ import annotations

from typing import Dict, Tuple

from gsmsdr_ns.bench.method_base import (
    BASES,
    MethodSpec,
    apply_overrides,
    base_config,
    make_method,
    set_lr_decay,
    set_pose_refinement,
)


def _view_kernels_method(sizes: Tuple[int, int, int]) -> MethodSpec:
    """``view-k<K>``: mode view with kernels of ``sizes`` px (HPKO 1/4, 1/2, full resolution; K the last)."""
    slashed = "/".join(str(k) for k in sizes)
    return make_method(
        f"view-k{sizes[-1]}",
        f"per-view kernels, kernels {slashed}",
        "gsmsdr",
        f"mode view with kernels of {' / '.join(str(k) for k in sizes)} px (HPKO 1/4, 1/2, full resolution)",
        mode="view",
        kernel_sizes=sizes,
    )


# final learning rates the bench's decays end at: 1/100 of the presets' constant rates for these groups
_DECAYED_FINAL_LR = {"blur_shake": 1e-3, "blur_view_kernels": 3e-4}


def _decayed_groups(groups: Tuple[str, ...]) -> Tuple[Tuple[str, float], ...]:
    """``MethodSpec.lr_final`` for decaying ``groups`` to :data:`_DECAYED_FINAL_LR`."""
    return tuple((group, _DECAYED_FINAL_LR[group]) for group in groups)


def _late_decay_method(name: str, what: str, doc_start: str, groups: Tuple[str, ...]) -> MethodSpec:
    """A ``gsmsdr-cpu`` variant whose ``groups``' learning rates are held until 0.6 of the run (full resolution
    starts at 0.5), then decayed 100x by its end."""
    return MethodSpec(
        name,
        f"gsmsdr-cpu, {what} decayed late",
        "gsmsdr-cpu",
        (),
        False,
        f"{doc_start} held until 0.6 of the run (full resolution starts at 0.5), then decayed 100x by its end",
        lr_final=_decayed_groups(groups),
        lr_hold_fraction=0.6,
    )


METHODS: Dict[str, MethodSpec] = {
    m.name: m
    for m in (
        make_method("plain", "plain (3DGS)", "plain", "plain Gaussians (degradation sharp) on the degraded images"),
        MethodSpec(
            "plain-poses",
            "plain + pose refinement",
            "plain",
            (),
            False,
            "plain Gaussians with nerfstudio's camera optimizer (SO3xR3) on every training view",
            pose_refinement="all",
        ),  # fmt: skip
        make_method(
            "msd-only", "MSD-only", "gsmsdr", "HPKO heads on BAGS' plain CNN (no GAKA/SAFM/MCA)", mode="msd_only"
        ),
        make_method(
            "re-only", "RE-only", "gsmsdr", "MAAN features, one full-resolution kernel scale (no HPKO)", mode="re_only"
        ),  # fmt: skip
        make_method("full", "GS-MSDR (full)", "gsmsdr", "the gsmsdr preset: MAAN + HPKO, with per-view kernels"),
        make_method(
            "full-fallback",
            "GS-MSDR (full) + per-image fallback",
            "gsmsdr",
            "full; a view trains plain steps until its blur model explains its photo better than the sharp render",
            fallback=True,
        ),  # fmt: skip
        make_method(
            "full-fallback-coarse",
            "GS-MSDR (full) + per-image fallback, errors at sigma 1",
            "gsmsdr",
            "full-fallback, both errors measured after a 1-pixel Gaussian blur of photo and renders",
            fallback=True,
            fallback_sigma=1.0,
        ),
        make_method(
            "full-anchor",
            "GS-MSDR (full) + sharp anchor 0.25",
            "gsmsdr",
            "full; a quarter of the plain loss on the sharp render beside the blurred render's",
            sharp_anchor_weight=0.25,
        ),
        make_method(
            "full-lens-early",
            "GS-MSDR (full), thin lens from the field's warm-up",
            "gsmsdr",
            "full with the thin lens from the end of the field's warm-up instead of the end of densification",
            thin_lens_start="warmup",
        ),
        MethodSpec(
            "full-poses",
            "GS-MSDR (full) + pose refinement",
            "gsmsdr",
            (),
            False,
            "full with nerfstudio's camera optimizer (SO3xR3) on the degraded views",
            pose_refinement="degraded",
        ),  # fmt: skip
        make_method(
            "full-per-pixel",
            "full, features at every pixel",
            "gsmsdr",
            "full with the feature network at every pixel (feature_downsample 1, the paper's field)",
            feature_downsample=1,
        ),  # fmt: skip
        make_method(
            "full-grid4k",
            "full, feature grid of at most 4096 cells",
            "gsmsdr",
            "full with the feature grid capped at 4096 cells, named (the default since the cap became one; the "
            "published grid4k suites name it)",
            feature_grid_cells=4096,
        ),  # fmt: skip
        MethodSpec(
            "cpu-poses",
            "gsmsdr-cpu + pose refinement",
            "gsmsdr-cpu",
            (),
            False,
            "gsmsdr-cpu with nerfstudio's camera optimizer (SO3xR3) on every training view",
            pose_refinement="all",
        ),  # fmt: skip
        make_method(
            "cpu-shake",
            "gsmsdr-cpu + camera shake paths",
            "gsmsdr-cpu",
            "gsmsdr-cpu with the render margin and a learnt camera rotation path (no translation) before the "
            "per-view kernels: the preset from the paths' adoption to the parallax translations' (the published "
            "shake suites name it)",
            render_margin=True,
            camera_shake=True,
            shake_translation=False,
        ),  # fmt: skip
        MethodSpec(
            "cpu-shake-decay",
            "gsmsdr-cpu, shake paths' rate decayed",
            "gsmsdr-cpu",
            (),
            False,
            "gsmsdr-cpu with the camera rotation paths' learning rate decayed 100x over the run (1e-1 to 1e-3)",
            lr_final=_decayed_groups(("blur_shake",)),
        ),  # fmt: skip
        MethodSpec(
            "cpu-decay",
            "gsmsdr-cpu, shake and kernel rates decayed",
            "gsmsdr-cpu",
            (),
            False,
            "gsmsdr-cpu with the rotation paths' and per-view kernels' learning rates decayed 100x over the run",
            lr_final=_decayed_groups(("blur_shake", "blur_view_kernels")),
        ),  # fmt: skip
        _late_decay_method(
            "cpu-late-decay",
            "shake and kernel rates",
            "gsmsdr-cpu with the shake paths' and per-view kernels' learning rates",
            ("blur_shake", "blur_view_kernels"),
        ),
        _late_decay_method(
            "cpu-late-path-decay",
            "shake rates",
            "cpu-late-decay with the per-view kernels at their constant rate: the shake paths' rate alone",
            ("blur_shake",),
        ),
        _late_decay_method(
            "cpu-late-kernel-decay",
            "kernel rates",
            "cpu-late-decay with the shake paths at their constant rate: the per-view kernels' rate alone",
            ("blur_view_kernels",),
        ),
        make_method(
            "cpu-shake17",
            "gsmsdr-cpu, 17 shake samples",
            "gsmsdr-cpu",
            "gsmsdr-cpu with the render warped to 17 time samples of each rotation path instead of 9",
            shake_samples=17,
        ),  # fmt: skip
        make_method(
            "cpu-shake-move",
            "gsmsdr-cpu + translating shake paths",
            "gsmsdr-cpu",
            "gsmsdr-cpu whose shake paths also move the camera (the warp reads the render's depth), the "
            "translations moving every pixel (not only what differs from the median depth)",
            shake_translation=True,
            shake_parallax=False,
        ),  # fmt: skip
        make_method(
            "cpu-shake-move-late",
            "gsmsdr-cpu + translating shake paths from densify end",
            "gsmsdr-cpu",
            "cpu-shake-move whose paths start translating when the Gaussians stop densifying (the render's depth has "
            "formed); they rotate only until then",
            shake_translation=True,
            shake_translation_start="densify_end",
            shake_parallax=False,
        ),  # fmt: skip
        make_method(
            "cpu-shake-parallax",
            "gsmsdr-cpu + parallax-only shake translations",
            "gsmsdr-cpu",
            "cpu-shake-move whose translations move the image relative to the render's median depth only (the "
            "rotation path carries the blur at that depth), named (the preset's since it paid)",
            shake_translation=True,
            shake_parallax=True,
        ),  # fmt: skip
        make_method(
            "cpu-shake-occlusion",
            "gsmsdr-cpu + occluding shake translations",
            "gsmsdr-cpu",
            "cpu-shake-parallax whose time samples read the render along the depth each sample's camera sees (a "
            "z-buffer; a near surface smears outward over the background) instead of the render's depth per pixel",
            shake_translation=True,
            shake_parallax=True,
            shake_occlusion=True,
        ),  # fmt: skip
        make_method(
            "cpu-kernel-centred",
            "gsmsdr-cpu, kernels centred after the path",
            "gsmsdr-cpu",
            "gsmsdr-cpu whose per-view kernels after the shake path are centred on exact mid-exposure poses too (the "
            "path through the pose carries the blur's shift; a free kernel could shift each view's image)",
            kernel_centre_after_shake=True,
        ),  # fmt: skip
        make_method(
            "cpu-shake-true-paths",
            "gsmsdr-cpu, true shake paths (diagnostic)",
            "gsmsdr-cpu",
            "cpu-shake-move whose rotation and translation paths are the generated shake's recorded ones (the "
            "closest cubics), not trained: what learning the paths costs (scenes with shake records only)",
            shake_translation=True,
            shake_parallax=False,
            shake_paths="records",
        ),  # fmt: skip
        make_method(
            "cpu-shake-true-occlusion17",
            "gsmsdr-cpu, true shake paths, occluding, 17 samples (diagnostic)",
            "gsmsdr-cpu",
            "cpu-shake-true-paths with the occluding warp at 17 time samples (the true 6-DoF path read at 17 samples "
            "explains the generated shake's photos to 40.5 dB, at 9 to 37.6): how close the best blur model comes "
            "to the sharp bound (scenes with shake records only)",
            shake_translation=True,
            shake_parallax=False,
            shake_occlusion=True,
            shake_samples=17,
            shake_paths="records",
        ),  # fmt: skip
        make_method(
            "cpu-shake-occlusion17",
            "gsmsdr-cpu + occluding shake translations, 17 shake samples",
            "gsmsdr-cpu",
            "cpu-shake-occlusion with the render warped to 17 time samples of each path instead of 9 (the true "
            "6-DoF path of the generated shake explains its photos to 37.6 dB at 9 samples, 40.5 at 17)",
            shake_translation=True,
            shake_parallax=True,
            shake_occlusion=True,
            shake_samples=17,
        ),  # fmt: skip
        make_method(
            "cpu-path-weighted",
            "gsmsdr-cpu, path in the deconvolved loss",
            "gsmsdr-cpu",
            "gsmsdr-cpu whose deconvolved residual loss weighs by the rotation path's mean kernel composed with the "
            "per-view kernels' (gsmsdr-cpu at 8604905)",
            deconvolved_loss_on_shake=True,
        ),  # fmt: skip
        make_method(
            "cpu-path-weighted-d05",
            "gsmsdr-cpu, path in the deconvolved loss, degraded densification x0.5",
            "gsmsdr-cpu",
            "cpu-path-weighted whose degraded views' densification gradient is halved (the loss's stronger "
            "gradients otherwise split more Gaussians)",
            model_overrides=(("degraded_densify_grad_scale", 0.5),),
            deconvolved_loss_on_shake=True,
        ),  # fmt: skip
        make_method(
            "cpu-path-weighted-eps04",
            "gsmsdr-cpu, path in the deconvolved loss, eps 0.04",
            "gsmsdr-cpu",
            "cpu-path-weighted with the deconvolved loss's Wiener regulariser 0.04 instead of 0.01 (its weight at "
            "most 5x instead of 10x where the blur removes a frequency)",
            deconvolved_loss_eps=0.04,
            deconvolved_loss_on_shake=True,
        ),  # fmt: skip
        make_method(
            "cpu-paper-loss",
            "gsmsdr-cpu, the paper's loss alone",
            "gsmsdr-cpu",
            "gsmsdr-cpu without the deconvolved residual loss (deconvolved_loss_weight 0)",
            deconvolved_loss_weight=0.0,
        ),  # fmt: skip
        make_method(
            "cpu-kernels",
            "gsmsdr-cpu, per-view kernels alone",
            "gsmsdr-cpu",
            "gsmsdr-cpu without the camera rotation paths and the render margin (the preset before they paid)",
            render_margin=False,
            camera_shake=False,
        ),  # fmt: skip
        make_method(
            "full-cells4",
            "full, 4 px feature cells at any size",
            "gsmsdr",
            "full with the feature grid at 4 px cells on every render, however large (feature_grid_cells 0, the "
            "default before the 4096-cell cap)",
            feature_grid_cells=0,
        ),  # fmt: skip
        make_method(
            "full-uncentred",
            "GS-MSDR (full), kernels not centred",
            "gsmsdr",
            "full without the kernel-centre regulariser (kernel_centre_weight 0)",
            kernel_centre_weight=0.0,
        ),
        make_method(
            "full-lens-unknown",
            "GS-MSDR (full), thin lens on blur of unknown kind",
            "gsmsdr",
            "full with the thin lens before the field on images whose kind of blur is unknown",
            thin_lens_for_unknown_kind=True,
        ),  # fmt: skip
        make_method(
            "full-paper-loss",
            "GS-MSDR (full), the paper's loss alone",
            "gsmsdr",
            "full without the deconvolved residual loss (deconvolved_loss_weight 0)",
            deconvolved_loss_weight=0.0,
        ),
        make_method(
            "full-lens-paper-loss",
            "GS-MSDR (full), no deconvolved loss on the lens",
            "gsmsdr",
            "full without the deconvolved residual loss on images the thin lens blurs (deconvolved_loss_on_lens False)",
            deconvolved_loss_on_lens=False,
        ),
        make_method(
            "full-margin",
            "GS-MSDR (full), render margin",
            "gsmsdr",
            "full rendering the kernel's half-width beyond every border of a blurred view (render_margin)",
            render_margin=True,
        ),  # fmt: skip
        make_method(
            "full-shake",
            "GS-MSDR (full), camera shake paths",
            "gsmsdr",
            "full-margin with a learnt camera rotation path before the field on views that may be shaken",
            render_margin=True,
            camera_shake=True,
        ),  # fmt: skip
        MethodSpec(
            "full-true",
            "GS-MSDR (full, true records)",
            "gsmsdr",
            (),
            False,
            "full with the true degradation records of a real-photo scene (elsewhere the same as full)",
            true_records=True,
        ),  # fmt: skip
        make_method(
            "-view",
            "-view kernels",
            "gsmsdr",
            "full without per-view kernels (the paper's blur field)",
            view_kernels=False,
        ),  # fmt: skip
        make_method(
            "view",
            "per-view kernels (mode view)",
            "gsmsdr",
            "one kernel per training view (mask 1), no feature network (fast)",
            mode="view",
        ),  # fmt: skip
        *(_view_kernels_method(sizes) for sizes in ((13, 25, 49), (9, 17, 33), (7, 13, 25))),
        make_method("-gaka", "-GAKA", "gsmsdr", "full without Global-Aware Kernel Attention", gaka=False),
        make_method("-safm", "-SAFM", "gsmsdr", "full without the Spatial Adaptive Fusion Module", safm=False),
        make_method("-mca", "-MCA", "gsmsdr", "full without the Multi-modal Context Adapter", mca=False),
        make_method("-rgbd", "-RGBD", "gsmsdr", "full with an RGB-only feature network (no depth input)", rgbd=False),
        make_method("gsmsdr-lite", "gsmsdr-lite", "gsmsdr-lite", "the gsmsdr-lite preset (half-width blur field)"),
        make_method(
            "gsmsdr-cpu",
            "gsmsdr-cpu",
            "gsmsdr-cpu",
            "the gsmsdr-cpu preset (mode view, kernels 9/17/33; the suite's schedule replaces the preset's own)",
        ),  # fmt: skip
        MethodSpec(
            "sharp-degraded-poses",
            "sharp, degraded photos' poses (bound)",
            "sharp",
            (),
            True,
            "plain Gaussians on the sharp photos, posed and undistorted by the degraded photos' "
            "structure-from-motion (real-photo scenes; elsewhere the same as sharp)",
            degraded_poses=True,
        ),  # fmt: skip
        make_method(
            "sharp",
            "sharp (upper bound)",
            "sharp",
            "plain Gaussians on the sharp images of the same scene",
            sharp_data=True,
        ),  # fmt: skip
    )
}
"""Suite method names -> what they train. Order = row order of the tables."""

TABLE7_METHODS = (("plain", "Baseline (plain)"), ("msd-only", "MSD-only"), ("re-only", "RE-only"),
                  ("full", "GS-MSDR (full)"))  # fmt: skip
"""Table 7 rows: baseline, multi-scale deblurring only, resolution enhancement only, both."""
TABLE6_METHODS = ("plain", "msd-only", "-gaka", "-safm", "-mca", "-rgbd", "re-only", "full")
"""Table 6 rows (module check marks); ``re-only`` is the paper's -HPKO row."""


def method_spec(name: str) -> MethodSpec:
    """The registered method ``name``; ValueError naming the valid names otherwise."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid: {', '.join(METHODS)}")
    return METHODS[name]


# BASES, MethodSpec, apply_overrides, base_config, set_*: defined in method_base, importable from here too
__all__ = ["BASES", "METHODS", "MethodSpec", "TABLE6_METHODS", "TABLE7_METHODS", "apply_overrides", "base_config",
           "method_spec", "set_lr_decay", "set_pose_refinement"]  # fmt: skip
