"""The fitted kind-of-blur ensemble: its JSON form and evaluation, the fit command on evaluation sets written to disk,
and the estimate reading a fitted file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gsmsdr_ns.estimate import EstimateConfig, estimate_degradations
from gsmsdr_ns.estimate.fit_kind_model import FitKindModelCLI, FitSettings, collect_rows
from gsmsdr_ns.estimate.kind_model import (
    KIND_FEATURES,
    MISSING,
    ensemble_to_json,
    feature_matrix,
    load_kind_model,
    log_odds,
    motion_probability,
    parse_ensemble,
)
from gsmsdr_ns.estimate.records import estimate_fingerprint
from gsmsdr_ns.io.images import write_image
from test_estimate import defocus_by, dwelling_shake, motion_blur, sharp_views


def _stump(feature: int, threshold: float, low: float, high: float) -> dict:
    return {"left": [1, -1, -1], "right": [2, -1, -1], "feature": [feature, 0, 0],
            "threshold": [threshold, -2.0, -2.0], "value": [0.0, low, high]}  # fmt: skip


def test_an_ensemble_sums_its_trees_leaves_as_log_odds():
    text = ensemble_to_json(["a", "b"], 0.5, 0.1, [_stump(0, 0.3, -4.0, 6.0), _stump(1, 2.0, 1.0, -1.0)])
    model = parse_ensemble(text)
    X = np.array([[0.1, 5.0], [0.9, 0.0], [MISSING, MISSING]])
    # row 0: left of the first stump (-4), right of the second (-1); row 1: 6 and 1; missing goes left (-4, 1)
    assert np.allclose(log_odds(model, X), [0.5 - 0.5, 0.5 + 0.7, 0.5 - 0.3])
    assert np.allclose(motion_probability(model, X), 1 / (1 + np.exp(-log_odds(model, X))))
    assert parse_ensemble(text).digest == model.digest != parse_ensemble(text.replace("0.5", "0.25", 1)).digest


def test_missing_evidence_becomes_the_missing_value():
    X = feature_matrix([{"a": 1.5, "b": None}, {"a": float("nan"), "b": float("inf")}], ("a", "b", "c"))
    assert X.tolist() == [[1.5, MISSING, MISSING], [MISSING, MISSING, MISSING]]


def test_a_bad_model_file_is_named(tmp_path):
    bad = tmp_path / "model.json"
    bad.write_text(json.dumps({"features": ["a"], "base": 0, "learning_rate": 1, "trees": [_stump(3, 0, 0, 0)]}))
    with pytest.raises(ValueError, match="model.json"):
        load_kind_model(str(bad))
    with pytest.raises(FileNotFoundError, match="missing.json"):
        load_kind_model(str(tmp_path / "missing.json"))
    elsewhere = tmp_path / "other.json"
    elsewhere.write_text(ensemble_to_json(["not_measured"], 0.0, 1.0, [_stump(0, 0.0, 1.0, -1.0)]))
    views = sharp_views()[:4]
    with pytest.raises(ValueError, match="not_measured"):
        estimate_degradations(views + [motion_blur(views[0])], EstimateConfig(kind_model=str(elsewhere)))


def test_the_builtin_model_reads_the_estimate_evidence_and_keys_the_cache():
    model = load_kind_model("")
    assert model.features == KIND_FEATURES and len(model.trees) > 10
    assert estimate_fingerprint()["kind_model_digest"] == model.digest
    assert "kind_model_digest" not in estimate_fingerprint(EstimateConfig(kind_from="rules"))


def _evaluation_set(root: Path, offset: int) -> Path:
    """An evaluation set as gsmsdr_ns.estimate.evaluate writes it: two scenes of 4 sharp views and 4 blurred ones
    with true records (one shaken scene, one defocused scene)."""
    views = sharp_views()
    for kind in ("motion", "defocus"):
        scene = root / f"synth-{kind}"
        (scene / "images").mkdir(parents=True)
        records = {}
        for i, view in enumerate(views):
            name = f"view_{i:02d}.png"
            if i < 4:
                image, effects = view, {}
            elif kind == "motion":
                image = dwelling_shake(view, 9 + offset + i, 0.7 * i) if i % 2 else motion_blur(view)
                effects = {"motion": {"blur_px": 9.0}}
            else:
                image, effects = defocus_by(view, 2.5 + 0.5 * (i - 4) + 0.25 * offset), {"defocus": {"radius_px": 3}}
            write_image(scene / "images" / name, image)
            records[name] = {"degraded": bool(effects), "effects": effects}
        (scene / "degradation.json").write_text(json.dumps({"version": 1, "images": records}), encoding="utf8")
    return root


@pytest.fixture(scope="module")
def evaluation_sets(tmp_path_factory) -> tuple[Path, Path]:
    """Two evaluation sets (see :func:`_evaluation_set`), written once for this module's tests (read only)."""
    root = tmp_path_factory.mktemp("sets")
    return _evaluation_set(root / "A", 0), _evaluation_set(root / "B", 1)


def test_the_fit_command_writes_an_ensemble_the_estimate_reads(evaluation_sets, tmp_path, capsys):
    sets = evaluation_sets
    rows = collect_rows(sets)
    assert len(rows.motion) == 16 and rows.motion.sum() == 8 and set(rows.group) == {"A", "B"}
    out = tmp_path / "fitted" / "kind_model.json"
    FitKindModelCLI(work=sets, out=out, settings=FitSettings(trees=20, depth=2, subsample=1.0)).main()
    printed = capsys.readouterr().out
    assert "| all | generated | 16 |" in printed  # the leave-one-set-out tables: per set, then by threshold
    sweep = [line for line in printed.splitlines() if line.startswith("| 0.")]
    assert [line.split(" | ")[0] for line in sweep] == ["| 0.5", "| 0.55", "| 0.6", "| 0.65", "| 0.7", "| 0.75", "| 0.8"]
    assert sweep[0].endswith("| 0 / 0 |")  # at 0.5 every kind is named: none unknown
    assert [p.name for p in out.parent.iterdir()] == ["kind_model.json"]  # no temporary file left behind
    views = sharp_views()
    images = views[:4] + [motion_blur(views[4]), dwelling_shake(views[5], 10, 2.0), defocus_by(views[6], 3.0),
                          defocus_by(views[7], 3.5)]  # fmt: skip
    estimates = estimate_degradations(images, EstimateConfig(kind_model=str(out)))
    assert [e.label for e in estimates] == ["sharp"] * 4 + ["motion"] * 2 + ["defocus"] * 2
    assert all(e.motion_probability > 0.6 for e in estimates[4:6])
    assert all(e.motion_probability < 0.4 for e in estimates[6:])
    assert all(e.motion_probability is None for e in estimates[:4])  # not blurred: not judged
    # a probability no image reaches leaves every kind unknown, the images still blurred
    unsure = estimate_degradations(images, EstimateConfig(kind_model=str(out), kind_probability=1.01))
    assert all(e.label == "unknown" and e.blurred is True for e in unsure[4:])


def test_the_fit_refuses_sets_without_both_kinds(evaluation_sets, tmp_path):
    root = tmp_path / "A"
    shutil.copytree(evaluation_sets[0] / "synth-motion", root / "synth-motion")  # shaken views only
    with pytest.raises(ValueError, match="one kind of blur"):
        FitKindModelCLI(work=(root,), out=tmp_path / "m.json", cross_validate=False).main()
    assert not (tmp_path / "m.json").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="empty holds no scene"):
        collect_rows((tmp_path / "empty",))


def test_the_fit_trains_on_exactly_what_the_estimate_reads(evaluation_sets):
    from gsmsdr_ns.estimate.fit_kind_model import scene_rows
    from gsmsdr_ns.estimate.records import read_folder

    scene = evaluation_sets[0] / "synth-motion"
    rows, motion = scene_rows(scene)
    assert len(rows) == 4 and all(motion)
    names, images = read_folder(scene / "images")
    estimates = estimate_degradations(images)
    judged = [e.motion_probability for e in estimates if e.motion_probability is not None]
    assert len(judged) == 4
    # the same numbers through the built-in ensemble give the estimate's own probabilities
    assert np.allclose(motion_probability(load_kind_model(""), feature_matrix(rows)), judged)
