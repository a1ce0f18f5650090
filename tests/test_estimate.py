"""Per-image degradation estimate: labels on real images written to disk, the upsampling factor, the
gsmsdr-estimate CLI's records (valid for the data reader, true records kept, atomic) and bad input."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import skimage.data
import torch

from gsmsdr_ns.data.degradation import load_degradation_json, match_entries, record_from_entry
from gsmsdr_ns.degrade.kernels import convolve_psf, disk_blur, motion_kernel_from_trajectory
from gsmsdr_ns.estimate import EstimateConfig, estimate_degradations
from gsmsdr_ns.estimate.classify import threshold_stages
from gsmsdr_ns.estimate.cli import parse
from gsmsdr_ns.estimate.edges import edge_width
from gsmsdr_ns.estimate.evidence import measure_images, set_evidence
from gsmsdr_ns.estimate.image_ops import to_gray
from gsmsdr_ns.estimate.records import (
    CACHE_FILE,
    ESTIMATED,
    estimate_entries,
    estimate_scene_records,
    read_folder,
)
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.images import write_image
from gsmsdr_ns.ops.mixres import apply_mixres

# A hand-held capture: views of one scene from slightly shifted positions (crops of a real photo).
OFFSETS = [(0, 0), (16, 40), (32, 80), (48, 120), (64, 20), (100, 60), (120, 100), (80, 128)]
CROP = (288, 384)


def _tensor(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32) / 255.0).permute(2, 0, 1)[None]


def _uint8(x: torch.Tensor) -> np.ndarray:
    return (x[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)


def sharp_views() -> list[np.ndarray]:
    photo = skimage.data.astronaut()
    return [photo[y : y + CROP[0], x : x + CROP[1]].copy() for y, x in OFFSETS]


def motion_blur(rgb: np.ndarray) -> np.ndarray:
    path = np.stack([np.linspace(-5, 5, 21), np.linspace(-2, 2, 21)], axis=1)  # an 11 px shake, mostly along x
    return _uint8(convolve_psf(_tensor(rgb), motion_kernel_from_trajectory(path).float()))


def defocus(rgb: np.ndarray) -> np.ndarray:
    return defocus_by(rgb, 4.0)


def defocus_by(rgb: np.ndarray, radius: float) -> np.ndarray:
    return _uint8(disk_blur(_tensor(rgb), radius))


def upsampled(rgb: np.ndarray, factor: int) -> np.ndarray:
    return _uint8(apply_mixres(_tensor(rgb), factor))


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """images/ of 8 sharp views + one motion-blurred, one defocused and one 3x-upsampled copy -> (scene, truth)."""
    scene = tmp_path_factory.mktemp("capture")
    (scene / "images").mkdir()
    views = sharp_views()
    images = {f"view_{i:02d}.png": v for i, v in enumerate(views)}
    images["view_20.png"] = motion_blur(views[1])
    images["view_21.png"] = defocus(views[2])
    images["view_22.png"] = upsampled(views[3], 3)
    for name, rgb in images.items():
        write_image(scene / "images" / name, rgb)
    truth = {n: "sharp" for n in images}
    truth.update({"view_20.png": "motion", "view_21.png": "defocus", "view_22.png": "mixres"})
    return scene, truth


def test_capture_is_labelled(capture):
    scene, truth = capture
    entries = estimate_entries(scene / "images")
    labels = {n: e["estimate"]["label"] for n, e in entries.items()}
    assert labels == truth
    assert entries["view_22.png"]["effects"]["mixres"]["factor"] == 3
    assert entries["view_20.png"]["estimate"]["anisotropy"] > entries["view_21.png"]["estimate"]["anisotropy"]
    for name, entry in entries.items():
        assert entry["degraded"] == (truth[name] != "sharp")
        assert entry["source"] == ESTIMATED
        assert 0.0 <= entry["estimate"]["confidence"] <= 1.0


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_upsampled_image_gets_its_factor(factor):
    views = sharp_views()[:5]
    estimates = estimate_degradations(views + [upsampled(views[0], factor)])
    assert [e.label for e in estimates] == ["sharp"] * 5 + ["mixres"]
    assert estimates[-1].mixres_factor == factor
    assert all(e.mixres_factor == 1 for e in estimates[:5])


def test_a_single_image_is_not_judged_sharp():
    (est,) = estimate_degradations(sharp_views()[:1])
    assert est.label == "unknown" and est.confidence == 0.0 and est.mixres_factor is None
    (up,) = estimate_degradations([upsampled(sharp_views()[0], 2)])
    assert up.label == "mixres" and up.mixres_factor == 2  # the grid needs no other image


def test_a_set_of_only_blurred_images_has_no_sharp_image():
    blurred = [defocus(v) for v in sharp_views()[:5]]
    estimates = estimate_degradations(blurred, EstimateConfig(min_reference_edge_ratio=1.25))
    assert not any(e.label == "sharp" for e in estimates)


def _copy_scene(src: Path, dst: Path) -> Path:
    (dst / "images").mkdir(parents=True)
    for p in (src / "images").iterdir():
        (dst / "images" / p.name).write_bytes(p.read_bytes())
    return dst


def test_cli_writes_records_the_reader_accepts_and_keeps_true_ones(capture, tmp_path):
    scene = _copy_scene(capture[0], tmp_path / "scene")
    true_entry = {"split": "train", "degraded": True, "effects": {"defocus": {"model": "disk", "radius_px": 4.0}}}
    doc = {"version": 1, "generator": "test", "images": {"view_21.png": true_entry}}
    (scene / "degradation.json").write_text(json.dumps(doc), encoding="utf8")

    parse(["--scene", str(scene)]).main()
    written = load_degradation_json(scene / "degradation.json")  # the data reader's own checks
    names = sorted(p.name for p in (scene / "images").iterdir())
    entries = match_entries(written, names, scene / "degradation.json")  # every image, no stray entry
    assert written["images"]["view_21.png"] == true_entry
    assert written["generator"] == "test"
    records = {n: record_from_entry(n, "train", e) for n, e in entries.items()}
    assert records["view_00.png"]["degraded"] is False and records["view_00.png"]["mixres_factor"] == 1
    assert records["view_20.png"]["degraded"] is True and set(records["view_20.png"]["effects"]) == {"motion"}
    assert records["view_22.png"]["mixres_factor"] == 3
    assert all(entries[n]["source"] == ESTIMATED for n in names if n != "view_21.png")
    assert not [p for p in scene.iterdir() if p.name.startswith(".")]  # no temp file left

    # a user's edit of an estimated entry is an estimate still: re-running replaces it; --replace-records
    # replaces true records too
    parse(["--scene", str(scene), "--replace-records"]).main()
    again = load_degradation_json(scene / "degradation.json")
    assert again["images"]["view_21.png"]["source"] == ESTIMATED
    assert again["images"]["view_21.png"]["effects"] == {"defocus": {"model": ESTIMATED}}


def test_cli_leaves_nothing_half_written_on_a_bad_image(capture, tmp_path):
    scene = _copy_scene(capture[0], tmp_path / "scene")
    before = json.dumps({"version": 1, "images": {"view_00.png": {"degraded": False, "effects": {}}}})
    (scene / "degradation.json").write_text(before, encoding="utf8")
    (scene / "images" / "view_05.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    with pytest.raises(InputError, match="view_05.png"):
        parse(["--scene", str(scene)]).main()
    assert (scene / "degradation.json").read_text(encoding="utf8") == before
    assert sorted(p.name for p in scene.iterdir()) == ["degradation.json", "images"]


def test_cli_refuses_an_unreadable_degradation_json(capture, tmp_path):
    scene = _copy_scene(capture[0], tmp_path / "scene")
    (scene / "degradation.json").write_text("{not json", encoding="utf8")
    with pytest.raises(InputError, match="degradation.json"):
        parse(["--scene", str(scene)]).main()
    assert (scene / "degradation.json").read_text(encoding="utf8") == "{not json"


def test_empty_folder_and_missing_arguments_give_clear_errors(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(InputError, match=f"no images in '{tmp_path / 'images'}'"):
        parse(["--images", str(tmp_path / "images")]).main()
    with pytest.raises(ValueError, match="exactly one of --scene"):
        parse([]).main()
    assert not (tmp_path / "degradation.json").exists()


def test_images_folder_is_printed_not_written(capture, tmp_path, capsys):
    scene = _copy_scene(capture[0], tmp_path / "scene")
    entries = parse(["--images", str(scene / "images")]).main()
    assert entries["view_20.png"]["estimate"]["label"] == "motion"
    assert sorted(p.name for p in scene.iterdir()) == ["images"]
    # each row shows the ensembles' probabilities and evidence: detail isotropy, directional loss
    printed = capsys.readouterr().out.splitlines()
    assert "p(d)" in printed[0] and "p(m)" in printed[0]
    evidence = entries["view_21.png"]["estimate"]
    cells = [c.strip() for c in next(line for line in printed if "view_21" in line).split("│")]
    for key in ("motion_probability", "isotropy", "directional_loss"):
        assert f"{evidence[key]:.2f}" in cells
    sharp = entries["view_00.png"]["estimate"]
    assert sharp["label"] == "sharp" and sharp["motion_probability"] is None
    row = next(line for line in printed if "view_00" in line)
    assert f"{sharp['degraded_probability']:.2f}" in [c.strip() for c in row.split("│")]


def test_scene_records_are_cached_until_an_image_changes(capture, tmp_path):
    scene = _copy_scene(capture[0], tmp_path / "scene")
    first = estimate_scene_records(scene)
    cache = scene / CACHE_FILE
    assert cache.is_file() and first["view_21.png"]["estimate"]["label"] == "defocus"
    doc = json.loads(cache.read_text(encoding="utf8"))
    doc["images"]["view_21.png"]["estimate"]["label"] = "from-cache"
    cache.write_text(json.dumps(doc), encoding="utf8")
    assert estimate_scene_records(scene)["view_21.png"]["estimate"]["label"] == "from-cache"

    write_image(scene / "images" / "view_21.png", sharp_views()[2])  # the defocused view replaced by a sharp one
    os.utime(scene / "images" / "view_21.png", ns=(1, 1))
    fresh = estimate_scene_records(scene)
    assert fresh["view_21.png"]["estimate"]["label"] == "sharp"
    assert not (scene / "degradation.json").exists()  # the cache never touches the scene's records


def test_views_of_different_content_get_their_kind_of_blur_from_the_image_alone():
    # Crops far apart show different things: the sharp views disagree about edge orientations as much as a blur
    # would, so comparing a view with the sharp ones cannot tell the kind. The blurred view's own directional loss
    # of detail still does: a shake takes detail along one direction in every region, a disk alike in all.
    photo = skimage.data.astronaut()
    offsets = [(0, 0), (40, 60), (80, 120), (120, 200), (200, 40), (260, 180), (300, 256), (160, 100)]
    views = [photo[y : y + 192, x : x + 256].copy() for y, x in offsets]
    images = views + [motion_blur(views[1]), defocus(views[2])]
    estimates = estimate_degradations(images)
    assert [e.label for e in estimates[-2:]] == ["motion", "defocus"]
    assert estimates[-2].directional_loss > 2 * max(e.directional_loss for e in estimates[:-2] + estimates[-1:])
    assert all(e.blurred is True and e.mixres_factor == 1 for e in estimates[-2:])
    # the views of the softest content fall between sharp and blurred: never called blurred, at most given a kind
    # with a low confidence (one blur simulated instead of both)
    assert all(e.blurred is not True and (e.label == "sharp" or e.confidence < 0.5) for e in estimates[:-2])


def test_a_set_with_one_sharp_view_names_a_kind_of_blur():
    # With one sharp view, how much content alone spreads the edge orientations is not measured (it is not zero);
    # each blurred view's own evidence names the kind.
    views = sharp_views()
    blurred = [motion_blur(v) for v in views[1:5]] + [defocus(v) for v in views[5:]]
    estimates = estimate_degradations([views[0]] + blurred)
    assert estimates[0].label == "sharp"
    assert [e.label for e in estimates[1:]] == ["motion"] * 4 + ["defocus"] * 3


def test_edge_width_is_the_blur_width_of_step_edges():
    board = np.repeat(skimage.data.checkerboard()[..., None], 3, axis=2)  # 25 px squares: isolated step edges
    sharp = edge_width(to_gray(board))
    blurred = edge_width(to_gray(_uint8(disk_blur(_tensor(board), 2.0))))
    assert 1.3 < sharp[0] <= sharp[1] < 2.0
    assert 3.0 < blurred[0] <= blurred[1] < 4.5  # a disk 4 px across
    assert all(math.isnan(w) for w in edge_width(to_gray(np.full((64, 64, 3), 128, np.uint8))))  # no edges


def test_a_view_blurred_in_part_is_not_called_sharp():
    # A lens focused on the upper part of the view: the strongest edges stay as sharp as in the other views, the
    # softest ones are wider than theirs.
    views = sharp_views()
    part = views[5].copy()
    part[230:] = defocus_by(views[5], 3.0)[230:]  # the lowest fifth out of focus
    estimates = estimate_degradations(views + [part])
    assert [e.label for e in estimates[:-1]] == ["sharp"] * len(views)
    # sharp by its sharpness, degraded by all the evidence together
    assert estimates[-1].degraded_probability > 0.9 and estimates[-1].label == "defocus"
    assert estimates[-1].blurred is not True
    # a strict soft-width ratio (the default is looser: sharp real photos of other content reach 1.3) leaves it
    # unknown by the thresholds alone (the shipped ensembles read evidence measured at the default ratio)
    config = EstimateConfig(soft_width_ratio=1.2)
    evidence = set_evidence(measure_images(views + [part], config), config)
    assert threshold_stages(evidence, config) == ["sharp"] * len(views) + ["unknown"]
    assert evidence.soft_width[-1] > config.soft_width_ratio > max(evidence.soft_width[:-1])


def test_the_spread_of_edge_widths_narrows_under_defocus(capture):
    scene, _ = capture
    names, images = read_folder(scene / "images")
    motion, defocused = names.index("view_20.png"), names.index("view_21.png")
    estimates = estimate_degradations(images)
    assert (estimates[motion].label, estimates[defocused].label) == ("motion", "defocus")
    # a defocus of the whole view widens every edge towards the disk's width: the spread of widths narrows (below
    # 0.85); a shake widens only the edges across it (about 1)
    assert estimates[defocused].width_spread < 0.85
    assert estimates[defocused].width_spread < estimates[motion].width_spread <= 1.1


def test_evaluation_scores_a_scene_against_its_records(capture, tmp_path):
    from tools.estimate.evaluate import format_table, score_scene

    scene = _copy_scene(capture[0], tmp_path / "scene")
    truth = {
        "view_20.png": {"motion": {"model": "kernel"}},
        "view_21.png": {"motion": {"model": "kernel"}},  # recorded as motion, blurred by a disk: a wrong kind
        "view_22.png": {"mixres": {"factor": 3}},
    }
    names = sorted(p.name for p in (scene / "images").iterdir())
    doc = {"version": 1, "images": {n: {"degraded": n in truth, "effects": truth.get(n, {})} for n in names}}
    (scene / "degradation.json").write_text(json.dumps(doc), encoding="utf8")
    score = score_scene(scene, "photos capture", EstimateConfig())
    assert (score.images, score.sharp_ok, score.unknown) == (11, 11, 0)
    assert (score.blur_total, score.blur_ok, score.blur_wrong) == (2, 1, 1)
    assert (score.mixres_total, score.mixres_ok) == (1, 1)
    assert len(score.mistakes) == 1 and score.mistakes[0].startswith("view_21.png: motion -> defocus")
    table = format_table([score, score_scene(scene, "synth copy", EstimateConfig())]).splitlines()
    assert [row.split(" | ")[0] for row in table[2:]] == ["| photos capture", "| synth copy", "| **photos**",
                                                          "| **synth**", "| **all**"]  # fmt: skip
    assert table[-1].split(" | ")[3:6] == [" 50.0% (2/4)", "2", " 50.0% (2/4)"]


def test_sobel_gradient_matches_kornia():
    from kornia.filters import spatial_gradient

    from gsmsdr_ns.estimate.image_ops import sobel_gradient

    gray = to_gray(sharp_views()[0]).float()
    expected = spatial_gradient(gray[None, None], mode="sobel", normalized=True)[0, 0]
    assert torch.allclose(sobel_gradient(gray), expected, atol=1e-6)
    assert float(expected.abs().max()) > 0.1  # a real photo has edges: the comparison is not between zeros


def _fern_set() -> list[np.ndarray]:
    """The 20 real fern photos at 252x189; photos 10-14 shaken along bent paths (7 px, five directions),
    photos 15-19 defocused by disks of radius 3-4 px (the first 10 stay sharp)."""
    from conftest import shared_fern

    from gsmsdr_ns.io.images import list_images, read_image

    folder = shared_fern() / "images_16"
    photos = [read_image(folder / n)[..., :3] for n in list_images(folder)]
    out = photos[:10]
    for k, photo in enumerate(photos[10:15]):
        angle = math.pi * k / 5
        t = np.linspace(-3.5, 3.5, 29)  # a 7 px shake that bends by 2.5 px
        along, across = t, 2.5 * (t / 3.5) ** 2
        path = np.stack([along * math.cos(angle) - across * math.sin(angle),
                         along * math.sin(angle) + across * math.cos(angle)], axis=1)  # fmt: skip
        out.append(_uint8(convolve_psf(_tensor(photo), motion_kernel_from_trajectory(path).float())))
    out += [defocus_by(photo, 3.0 + 0.25 * k) for k, photo in enumerate(photos[15:])]
    return out


def test_small_real_photos_get_their_kind_of_blur():
    # At 252x189 the sharp photos' per-orientation edge steepness differs too much from photo to photo to tell the
    # kind; the detail tensors, relative to the sharp photos' (views of one scene), still do.
    images = _fern_set()
    estimates = estimate_degradations(images)
    labels = [e.label for e in estimates]
    assert labels[:10] == ["sharp"] * 10 and labels[15:] == ["defocus"] * 5
    # a bent shake is nearer isotropic than a straight one: between the two limits the kind stays unknown
    assert labels[10:15].count("motion") >= 4 and set(labels[10:15]) <= {"motion", "unknown"}
    assert all(e.blurred is True for e in estimates[10:])
    assert max(e.isotropy for e in estimates[10:15]) < min(e.isotropy for e in estimates[15:])


def test_the_detail_tensor_shrinks_across_a_motion_and_alike_under_defocus():
    from gsmsdr_ns.estimate.direction import detail_tensor

    photo = sharp_views()[0]
    sharp = detail_tensor(to_gray(photo))
    shaken = detail_tensor(to_gray(_uint8(convolve_psf(_tensor(photo), motion_kernel_from_trajectory(
        np.stack([np.linspace(-4, 4, 33), np.zeros(33)], axis=1)).float()))))  # fmt: skip
    whiten = np.diag(np.diag(sharp) ** -0.5)  # nearly diagonal on this photo: enough to compare x with y
    rel = whiten @ shaken @ whiten
    assert rel[0, 0] < 0.7 * rel[1, 1]  # a horizontal shake took far more of the horizontal detail
    blurred = whiten @ detail_tensor(to_gray(defocus_by(photo, 3.0))) @ whiten
    assert 0.9 < blurred[0, 0] / blurred[1, 1] < 1.1
    assert np.isnan(detail_tensor(to_gray(np.full((64, 64, 3), 90, np.uint8)))).all()  # flat: undefined


def _blur_part(rgb: np.ndarray, radius: float, share: float = 2 / 3) -> np.ndarray:
    """rgb with its left `share` blurred by a disk (a lens focused on what the right part shows)."""
    out = rgb.copy()
    cut = int(rgb.shape[1] * share)
    out[:, :cut] = defocus_by(rgb, radius)[:, :cut]
    return out


def test_a_shake_takes_detail_along_one_direction_in_every_region():
    from gsmsdr_ns.estimate.direction import spectral_anisotropy, tile_detail_coherence

    photo = sharp_views()[0]
    along_x = motion_blur(photo)
    along_y = np.ascontiguousarray(motion_blur(photo.transpose(1, 0, 2)).transpose(1, 0, 2))
    measures = (tile_detail_coherence, spectral_anisotropy)
    for measure in measures:
        sharp, disk = measure(to_gray(photo)), measure(to_gray(defocus(photo)))
        x, y = measure(to_gray(along_x)), measure(to_gray(along_y))
        assert min(x, y) > 2 * max(sharp, disk)
        assert abs(x - y) < 0.35 * max(x, y)  # the direction of the shake does not matter, only that it has one
    assert math.isnan(tile_detail_coherence(to_gray(np.full((64, 64, 3), 90, np.uint8))))  # flat: undefined


def test_the_sharpest_region_of_a_view_focused_on_one_depth_stays_sharp():
    from gsmsdr_ns.estimate.edges import sharpest_region_width, step_edges

    photo = sharp_views()[0]

    def region(rgb):
        gray = to_gray(rgb)
        return sharpest_region_width(*step_edges(gray), tuple(gray.shape))

    sharp, part, whole = region(photo), region(_blur_part(photo, 3.0)), region(defocus_by(photo, 3.0))
    assert part < 1.15 * sharp and whole > 1.5 * sharp
    assert edge_width(to_gray(_blur_part(photo, 3.0)))[1] > 1.3 * edge_width(to_gray(photo))[1]  # yet soft edges
    assert math.isnan(region(np.full((64, 64, 3), 90, np.uint8)))


def test_a_view_blurred_in_part_only_is_named_defocus():
    # A shake blurs every region of the view; a lens focused on one depth leaves one region sharp.
    views = sharp_views()
    images = views[:6] + [_blur_part(v, 3.0) for v in views[6:]]
    estimates = estimate_degradations(images)
    assert [e.label for e in estimates[6:]] == ["defocus", "defocus"]
    assert all(e.sharpest_region <= 1.15 for e in estimates[6:])  # its sharpest region as narrow-edged as a sharp view
    assert all(e.label == "sharp" for e in estimates[:6])


def dwelling_shake(rgb: np.ndarray, length: float, angle: float) -> np.ndarray:
    """rgb shaken along a straight `length` px path at `angle` that the camera leaves slowly and crosses fast (it
    dwells near the start, as a hand does between jerks): a peaked line spread with a long tail."""
    s = length * np.linspace(0.0, 1.0, 61) ** 3 - length / 2
    path = np.stack([s * math.cos(angle), s * math.sin(angle)], axis=1)
    return _uint8(convolve_psf(_tensor(rgb), motion_kernel_from_trajectory(path).float()))


def test_the_blur_shape_measures():
    from gsmsdr_ns.estimate.direction import tile_detail_spread
    from gsmsdr_ns.estimate.edges import edge_rise_ratio

    photo = sharp_views()[0]
    shaken = [edge_rise_ratio(to_gray(dwelling_shake(photo, length, 0.3))) for length in (9, 12)]
    disks = [edge_rise_ratio(to_gray(defocus_by(photo, radius))) for radius in (2.0, 3.0, 4.0)]
    assert min(shaken) > 1.13 >= max(disks), (shaken, disks)
    assert 0.8 < min(disks)
    # fine detail over the tiles: a lens focused on part of the view keeps its spread, a blur of all of it narrows it
    spread = {name: tile_detail_spread(to_gray(rgb)) for name, rgb in [
        ("sharp", photo), ("part", _blur_part(photo, 3.0)), ("disk", defocus_by(photo, 3.0)),
        ("shake", motion_blur(photo)), ("dwell", dwelling_shake(photo, 12, 0.3))]}  # fmt: skip
    assert spread["part"] > 0.84 * spread["sharp"], spread
    assert max(spread["disk"], spread["shake"], spread["dwell"]) < 0.7 * spread["sharp"], spread
    flat = to_gray(np.full((64, 64, 3), 90, np.uint8))
    assert math.isnan(tile_detail_spread(flat)) and math.isnan(edge_rise_ratio(flat))
    assert math.isnan(edge_rise_ratio(to_gray(photo[:40, :40])))  # too few blurred step edges


def test_the_blur_shape_is_part_of_a_set_s_evidence():
    views = sharp_views()
    images = views[:4] + [dwelling_shake(views[4], 12, 0.4), dwelling_shake(views[5], 12, 2.0),
                          defocus_by(views[6], 3.0), defocus_by(views[7], 3.5)]  # fmt: skip
    estimates = estimate_degradations(images)
    assert [e.label for e in estimates[:4]] + [e.label for e in estimates[6:]] == ["sharp"] * 4 + ["defocus"] * 2
    assert all(e.blurred is True for e in estimates[4:])
    # the dwelling shakes' peaked edge profile, every blurred view's detail lost from every tile (relative to the
    # sharp views')
    assert min(e.edge_rise for e in estimates[4:6]) > 1.13 >= max(e.edge_rise for e in estimates[6:])
    assert all(e.detail_spread < 0.84 for e in estimates[4:])
    assert all(abs(e.detail_spread - 1.0) < 0.1 for e in estimates[:4])
