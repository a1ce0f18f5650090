"""The real-photo bench suite (configs/bench/real.yaml): its file parses, and a scene built from six real fern
photos (structure-from-motion on the sharp photos, gsmsdr-degrade, structure-from-motion on the degraded training
photos alone, the sharp test photos registered into that model) has the layout, poses and records each method
trains on. The slow test runs the suite end to end on that scene with nerfstudio's trainer."""

from __future__ import annotations

import json
import re
import shutil
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_fern
from skimage.filters import gaussian
from skimage.transform import resize

from gsmsdr_ns.bench.fingerprint import fingerprint
from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.real_scenes import DATA_DIR_ENV, RealSceneSpec, resolve_photos
from gsmsdr_ns.bench.suite_config import RunKey, SuiteConfigError, find_suite_file, load_suite
from gsmsdr_ns.blur.profile import DegradationProfile
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.images import read_image_float

NUM_PHOTOS = 6


def suite_text(methods: str = "[plain, full, full-true, sharp]", steps: int = 20) -> str:
    return textwrap.dedent(f"""\
        name: real-tiny
        scenes:
          - name: fern6-motion
            real: {{dataset: fern6, images: images_16, preset: motion-mild, hold: 3, train_downscale: 2}}
        methods: {methods}
        steps: [{steps}]
        eval_every: 10
        schedule: {{num_downscales: 0}}
        threads: 1
        lpips: false
        """)


@pytest.fixture(scope="module")
def photo_set(tmp_path_factory) -> Path:
    """A data folder holding ``fern6/images_16``: the first six fern photos (252x189)."""
    root = tmp_path_factory.mktemp("data")
    folder = root / "fern6" / "images_16"
    folder.mkdir(parents=True)
    for name in sorted(p.name for p in (shared_fern() / "images_16").iterdir())[:NUM_PHOTOS]:
        shutil.copyfile(shared_fern() / "images_16" / name, folder / name)
    return root


@pytest.fixture(scope="module")
def built(photo_set, tmp_path_factory) -> dict:
    """The scenes of ``full`` (estimated records), ``full-true``, ``sharp`` and ``sharp-degraded-poses`` on the six
    photos."""
    work = tmp_path_factory.mktemp("bench")
    config = work / "real-tiny.yaml"
    config.write_text(suite_text(), encoding="utf8")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(DATA_DIR_ENV, str(photo_set))
        suite = load_suite(config)
        scene = suite.scenes[0]
        logs: list = []
        methods = ("full", "full-true", "sharp", "plain", "sharp-degraded-poses")
        data = {m: scene.data(METHODS[m], work, logs.append) for m in methods}
    return {"suite": suite, "data": data, "logs": logs, "work": work}


def test_shipped_real_suite_parses() -> None:
    suite = load_suite(find_suite_file("real"))
    names = ["fern-motion", "fern-defocus", "fern-defocus-disk", "fern-defocus-disk-random", "fern-sharp"]
    assert [s.name for s in suite.scenes] == names
    motion, defocus, disk, disk_random, sharp = (s.real for s in suite.scenes)
    assert disk_random == disk and suite.scenes[3].random_init and not suite.scenes[2].random_init
    assert motion.dataset == "llff-fern" and motion.preset == "motion-strong" and sharp.preset == "sharp"
    assert defocus.preset == "defocus-strong" and disk.preset == "defocus-disk"
    assert motion.images == defocus.images == disk.images == sharp.images  # the YAML merge key
    assert motion.train_downscale == defocus.train_downscale == disk.train_downscale == sharp.train_downscale
    assert suite.methods == ["plain", "full", "sharp-degraded-poses", "sharp"]
    assert suite.steps == [3000] and len(suite.seeds) >= 3
    # the two bounds train on different photos: their records must not be taken for each other's
    assert fingerprint(suite, RunKey("fern-motion", "sharp", 3000, 0)) != fingerprint(
        suite, RunKey("fern-motion", "sharp-degraded-poses", 3000, 0)
    )
    assert suite.align_poses
    assert suite.threads == 1 and "registered" in suite.scenes[0].describe()


def test_shipped_real_size_suite_trains_fern_at_its_photos_size_and_a_600x400_scene() -> None:
    suite = load_suite(find_suite_file("real-size"))
    fern, generated = suite.scenes
    assert fern.real is not None and fern.real.train_downscale == 1 and fern.real.images == "images_8"
    assert fern.real.preset == "motion-strong"
    assert generated.spec is not None and (generated.spec.width, generated.spec.height) == (600, 400)
    assert generated.spec.variant == "motion-strong"
    bounds = ["sharp-degraded-poses", "sharp"]  # a perfect deblurring with the shaken photos' poses; the sharp photos
    assert suite.methods == ["plain", "full", "view", "gsmsdr-lite", "gsmsdr-cpu", *bounds]  # the registry's order
    assert all(scene.supports(METHODS[m]) for scene in suite.scenes for m in suite.methods)
    assert suite.threads == 2 and suite.eval_every > 0  # both threads; PSNR along the run, against wall time


def test_runs_that_train_on_estimated_records_rerun_when_the_estimate_changes(monkeypatch) -> None:
    import gsmsdr_ns.estimate.records as records

    suite = load_suite(find_suite_file("real"))
    keys = [RunKey("fern-motion", m, 3000, 0) for m in ("plain", "full", "sharp-degraded-poses", "sharp")]
    before = [fingerprint(suite, k) for k in keys]
    monkeypatch.setattr(records, "METHOD_VERSION", records.METHOD_VERSION + 1)
    after = [fingerprint(suite, k) for k in keys]
    # only full reads the estimate; plain and the bounds keep their records
    assert [b != a for b, a in zip(before, after)] == [False, True, False, False]


def test_real_ablations_share_the_real_suites_shaken_scene() -> None:
    """The diagnostic rows train on the very scene of the main suite (same spec and schedule: same records when run
    into the same output folder)."""
    real, ablations = (load_suite(find_suite_file(name)) for name in ("real", "real-ablations"))
    assert [s.name for s in ablations.scenes] == ["fern-motion"]
    assert ablations.scenes[0].real == real.scenes[0].real
    assert ablations.schedule_for(3000) == real.schedule_for(3000) and ablations.align_poses
    diagnostics = {"full-uncentred", "full-poses", "plain-poses", "full-lens-unknown", "full-paper-loss"}
    assert {"plain", "full"} | diagnostics <= set(ablations.methods)
    assert fingerprint(ablations, RunKey("fern-motion", "full", 3000, 0)) == fingerprint(
        real, RunKey("fern-motion", "full", 3000, 0)
    )


@pytest.mark.parametrize(
    "old, new, key",
    [
        ("preset: motion-mild", "preset: motion-blurry", "scenes[0].real.preset"),
        ("hold: 3", "hold: 1", "scenes[0].real.hold"),
        ("train_downscale: 2", "train_downscal: 2", "scenes[0].real.train_downscal"),
        ("images: images_16", "images: 16", "scenes[0].real.images"),
        ("    real:", "    path: x\n    real:", "scenes[0]"),
    ],
)
def test_invalid_real_scene_names_file_and_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(suite_text().replace(old, new), encoding="utf8")
    with pytest.raises(SuiteConfigError, match=re.escape(f"{path}: {key}:")):
        load_suite(path)


def test_missing_photo_set_says_where_it_looked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fern = shared_fern()  # found before the data folder is pointed elsewhere (it may be how fern is found)
    monkeypatch.setenv(DATA_DIR_ENV, str(tmp_path))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=rf"photo set 'no-such-set'.*{tmp_path}/no-such-set/images_16.*{DATA_DIR_ENV}"):
        resolve_photos(RealSceneSpec(dataset="no-such-set"))
    assert resolve_photos(RealSceneSpec(dataset=str(fern))) == fern / "images_16"


def test_each_method_gets_its_scene(built) -> None:
    data = built["data"]
    assert data["plain"] == data["full"] != data["full-true"] != data["sharp"]
    assert len({data[m] for m in ("full", "full-true", "sharp", "sharp-degraded-poses")}) == 4
    assert "motion-mild" in data["full"].name and "-sharp-" in data["sharp"].name
    assert "motion-mild" in data["sharp-degraded-poses"].name and "sharp-photos" in data["sharp-degraded-poses"].name
    assert not (data["sharp-degraded-poses"] / "degradation.json").exists()
    for folder in data.values():
        assert (folder / "hold=3").is_file() and (folder / "real_scene.json").is_file()
    assert not (data["full"] / "degradation.json").exists(), "the default method must estimate its records"
    doc = json.loads((data["full-true"] / "degradation.json").read_text(encoding="utf8"))
    splits = {n: e["split"] for n, e in doc["images"].items()}
    names = sorted(p.name for p in (data["full"] / "images").iterdir())
    assert [splits[n] for n in names] == ["test", "train", "train", "test", "train", "train"]
    assert all("motion" in doc["images"][n]["effects"] for n in names if splits[n] == "train")
    # the poses come from the degraded photos' structure-from-motion, not from the shake: kernels stay centred
    profiles = [DegradationProfile.from_metadata(doc["images"][n]) for n in names if splits[n] == "train"]
    assert profiles and all(p.motion and not p.exact_pose for p in profiles)
    (degraded,) = data["full"].parent.glob("*motion-mild*-degraded/degradation.json")  # gsmsdr-degrade's records
    source = json.loads(degraded.read_text(encoding="utf8"))
    assert any(e.get("effects", {}).get("motion", {}).get("reference") == "mid_exposure"
               for e in source["images"].values())  # fmt: skip
    assert any("registered" in line for line in built["logs"])


def test_methods_train_on_the_shrunk_copies_and_the_estimate_judges_the_full_size_photos(built, tmp_path) -> None:
    data, scene = built["data"], built["suite"].scenes[0]
    config = METHODS["full"].make_config(data["full"], tmp_path)
    scene.configure(config)
    parser = config.pipeline.datamanager.dataparser
    parser.data = config.pipeline.datamanager.data  # as the datamanager hands it over
    outputs = parser.setup().get_dataparser_outputs("train")
    assert {Path(f).parent for f in outputs.image_filenames} == {data["full"] / "images_2"}
    cache = json.loads((data["full"] / "degradation.estimated.json").read_text(encoding="utf8"))
    assert Path(cache["source"]) == data["full"] / "images"
    assert len(outputs.metadata["degradations"]) == 4


def test_a_new_estimate_that_changes_no_record_keeps_the_runs_record(built, tmp_path, monkeypatch) -> None:
    """A record of a run on estimated records, as train_and_record writes it (its numbers stand for a finished run),
    is re-keyed when only the estimate's fingerprint changed and the records it trained on are the same; it is rerun
    when they differ."""
    import gsmsdr_ns.estimate.records as records
    from gsmsdr_ns.bench.ledger import plan_runs, rekey_unchanged_estimates, training_records_digest
    from gsmsdr_ns.bench.records import load_record, record_path, write_json_atomic

    suite, work, out = built["suite"], built["work"], tmp_path / "out"
    key = RunKey("fern6-motion", "full", 20, 0)
    assert key in suite.runs()
    digest = training_records_digest(suite, key, work, tmp_path / "ns")
    old = fingerprint(suite, key)
    record = {"id": key.id, "fingerprint": old, "fingerprint_without_estimate": fingerprint(suite, key, estimate=False),
              "training_records": digest, "psnr": 20.0}  # fmt: skip
    write_json_atomic(record_path(out, key), record)
    assert key.id in plan_runs(suite, out).reused and not rekey_unchanged_estimates(suite, out, work, tmp_path / "ns")
    monkeypatch.setattr(records, "METHOD_VERSION", records.METHOD_VERSION + 1)  # a new estimate, the same labels
    assert fingerprint(suite, key) != old and key in plan_runs(suite, out).todo
    assert rekey_unchanged_estimates(suite, out, work, tmp_path / "ns") == [key.id]
    kept = load_record(record_path(out, key))
    assert kept["fingerprint"] == fingerprint(suite, key) and kept["rekeyed_from"] == [old] and kept["psnr"] == 20.0
    assert key.id in plan_runs(suite, out).reused
    # records that differ from what the run trained on: rerun
    write_json_atomic(record_path(out, key), {**record, "training_records": "0" * 16})
    assert not rekey_unchanged_estimates(suite, out, work, tmp_path / "ns") and key in plan_runs(suite, out).todo
    # a change outside the estimate (another step budget's schedule, say) is never forgiven
    write_json_atomic(record_path(out, key), {**record, "fingerprint_without_estimate": "0" * 16})
    assert not rekey_unchanged_estimates(suite, out, work, tmp_path / "ns")


def test_scenes_share_cameras_and_differ_only_where_they_should(built) -> None:
    data = built["data"]
    estimated, true = (read_colmap(data[m] / "sparse" / "0", tracks=True) for m in ("full", "full-true"))
    np.testing.assert_array_equal(estimated.w2c, true.w2c)
    assert set(estimated.camera_models) == {"PINHOLE"} and len(estimated.names) == NUM_PHOTOS
    assert len(estimated.points.xyz) > 50
    test_views = {estimated.names[i] for i in (0, 3)}
    # the test photos of the training scene observe no point: the model was built from the degraded photos alone
    assert not set(estimated.points.obs_view.tolist()) & {0, 3}
    facts = json.loads((data["full"] / "real_scene.json").read_text(encoding="utf8"))
    assert set(facts["test_views"]) == test_views and facts["training_poses_moved_by_registration"] < 1e-9
    for name in estimated.names:
        motion = read_image_float(data["full"] / "images_2" / name)
        sharp = read_image_float(data["sharp"] / "images_2" / name)
        for image in (motion, sharp):  # 252x189, resampled by the undistortion, then shrunk 2x
            assert 90 <= image.shape[1] <= 140 and 68 <= image.shape[0] <= 105, image.shape
        full = read_image_float(data["full"] / "images" / name)  # what the degradation estimate judges
        assert full.shape[:2] == (2 * motion.shape[0] + full.shape[0] % 2, 2 * motion.shape[1] + full.shape[1] % 2)
        blurred = float(np.abs(np.diff(motion, axis=1)).mean()) < 0.9 * float(np.abs(np.diff(sharp, axis=1)).mean())
        assert blurred == (name not in test_views), name


def _smoothed(image: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """image [H, W, 3] blurred by a Gaussian of ``sigma`` px: what a shake of a few px leaves comparable."""
    return gaussian(image, sigma=sigma, channel_axis=-1)


def test_sharp_photos_scene_has_the_degraded_runs_cameras(built) -> None:
    """The bound ``sharp-degraded-poses`` trains on the sharp photos undistorted and posed by the degraded photos'
    model: the same cameras as the degraded scene (the seeded mapping run again), the same test photos, sharper
    training photos that line up with the degraded ones (the sharp twin's, undistorted by its own run, do not)."""
    data = built["data"]
    degraded, bound = (read_colmap(data[m] / "sparse" / "0") for m in ("full", "sharp-degraded-poses"))
    assert bound.names == degraded.names
    np.testing.assert_array_equal(bound.w2c, degraded.w2c)
    np.testing.assert_array_equal(bound.intrinsics, degraded.intrinsics)
    np.testing.assert_array_equal(bound.sizes, degraded.sizes)
    facts = json.loads((data["sharp-degraded-poses"] / "real_scene.json").read_text(encoding="utf8"))
    for name in degraded.names:
        motion = read_image_float(data["full"] / "images_2" / name)
        sharp = read_image_float(data["sharp-degraded-poses"] / "images_2" / name)
        if name in facts["test_views"]:
            np.testing.assert_array_equal(sharp, motion)
            continue
        assert np.abs(np.diff(motion, axis=1)).mean() < 0.9 * np.abs(np.diff(sharp, axis=1)).mean(), name
        # the sharp twin's photo, stretched to this size: the same view through another run's camera
        twin = resize(read_image_float(data["sharp"] / "images_2" / name), motion.shape, anti_aliasing=True)
        aligned = float(np.abs(_smoothed(sharp) - _smoothed(motion)).mean())
        assert aligned < 0.5 * float(np.abs(_smoothed(twin) - _smoothed(motion)).mean()), name


def test_registered_test_poses_agree_with_the_sharp_run(built) -> None:
    """Test cameras registered into the degraded model, carried onto the sharp photos' own SfM run by the similarity
    of the training cameras (their mean rotation; scale and shift of their centres), land where that run put them:
    centres within 5% of the trajectory diameter, orientations within 1.5 degrees."""
    scenes = built["work"] / "scenes"
    sharp_run = read_colmap(next(scenes.glob("fern6-images_16-sfm-*")) / "sparse" / "0")
    degraded = read_colmap(built["data"]["full"] / "sparse" / "0")
    assert sharp_run.names == degraded.names
    train, test = [1, 2, 4, 5], [0, 3]
    u, _, vt = np.linalg.svd(sum(sharp_run.c2w[i, :3, :3] @ degraded.c2w[i, :3, :3].T for i in train))
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    src, tgt = degraded.c2w[:, :3, 3] @ rotation.T, sharp_run.c2w[:, :3, 3]
    src_c, tgt_c = src[train] - src[train].mean(0), tgt[train] - tgt[train].mean(0)
    scale = float(np.sum(src_c * tgt_c) / np.sum(src_c**2))
    mapped = scale * (src - src[train].mean(0)) + tgt[train].mean(0)
    diameter = np.linalg.norm(tgt[:, None] - tgt[None], axis=2).max()
    for i in test:
        assert np.linalg.norm(mapped[i] - tgt[i]) < 0.05 * diameter
        relative = rotation @ degraded.c2w[i, :3, :3] @ sharp_run.c2w[i, :3, :3].T
        angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
        assert angle < 1.5, angle


@pytest.mark.slow
def test_real_suite_end_to_end(photo_set, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from gsmsdr_ns.bench.ledger import training_records_digest
    from gsmsdr_ns.bench.runner import run_suite

    monkeypatch.setenv(DATA_DIR_ENV, str(photo_set))
    config = tmp_path / "real-tiny.yaml"
    config.write_text(suite_text("[plain, full, full-true, sharp]", steps=20), encoding="utf8")
    outcome_suite = load_suite(config)
    outcome = run_suite(outcome_suite, tmp_path / "out", progress=False, plots=False)
    assert not outcome.failed and len(outcome.trained) == 4
    by_method = {r["method"]: r for r in outcome.records}
    assert re.search(r"-estimated-l\d+$", by_method["full"]["data"])  # the scene without records
    # what a later estimate is checked against before this record is kept (rekey_unchanged_estimates)
    key = RunKey("fern6-motion", "full", 20, 0)
    assert by_method["full"]["training_records"] == training_records_digest(
        outcome_suite, key, tmp_path / "out", tmp_path / "ns"
    )
    assert "training_records" not in by_method["plain"]
    assert re.search(r"-true-l\d+$", by_method["full-true"]["data"])  # its twin with the true records
    assert all(np.isfinite(r["psnr"]) and r["num_test_views"] == 2 for r in outcome.records)
    assert "fern6-motion" in (tmp_path / "out" / "results.md").read_text(encoding="utf8")
