"""The fitted ensembles (kind of blur, degraded among sharp-looking images): their JSON form, provenance and
evaluation, the fit command on evaluation sets written to disk, and the estimate reading fitted files."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_estimate import defocus_by, dwelling_shake, motion_blur, sharp_views

from gsmsdr_ns.estimate import EstimateConfig, estimate_degradations
from gsmsdr_ns.estimate.ensemble import (
    KIND_FEATURES,
    MISSING,
    ensemble_to_json,
    evidence_matrix,
    load_degraded_model,
    load_kind_model,
    log_odds,
    make_provenance,
    parse_ensemble,
    probability,
)
from gsmsdr_ns.estimate.records import estimate_fingerprint
from gsmsdr_ns.io.images import write_image
from tools.estimate.fit_ensembles import FitEnsemblesCLI, FitSettings, collect_rows


def _stump(feature: int, threshold: float, low: float, high: float) -> dict:
    return {"left": [1, -1, -1], "right": [2, -1, -1], "feature": [feature, 0, 0],
            "threshold": [threshold, -2.0, -2.0], "value": [0.0, low, high]}  # fmt: skip


PROVENANCE = make_provenance(EstimateConfig(), ["test"], "none")
"""The provenance of a hand-made ensemble over evidence measured with the default config."""


def test_an_ensemble_sums_its_trees_leaves_as_log_odds():
    text = ensemble_to_json(["a", "b"], 0.5, 0.1, [_stump(0, 0.3, -4.0, 6.0), _stump(1, 2.0, 1.0, -1.0)], "motion")
    model = parse_ensemble(text)
    X = np.array([[0.1, 5.0], [0.9, 0.0], [MISSING, MISSING]])
    # row 0: left of the first stump (-4), right of the second (-1); row 1: 6 and 1; missing goes left (-4, 1)
    assert np.allclose(log_odds(model, X), [0.5 - 0.5, 0.5 + 0.7, 0.5 - 0.3])
    assert np.allclose(probability(model, X), 1 / (1 + np.exp(-log_odds(model, X))))
    assert parse_ensemble(text).digest == model.digest != parse_ensemble(text.replace("0.5", "0.25", 1)).digest


def test_the_package_imports_neither_the_research_tools_nor_scikit_learn():
    # the fitting needs scikit-learn, a test dependency only; the installed estimate reads the JSON with numpy
    code = ("import sys, gsmsdr_ns.estimate, gsmsdr_ns.estimate.cli, gsmsdr_ns.estimate.records; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('sklearn', 'tools')))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300)
    assert out.stdout.strip() == "[]"


def test_missing_evidence_becomes_the_missing_value():
    columns = {"a": np.array([1.5, np.nan]), "b": np.array([np.inf, 2.0]), "c": np.array([0.0, 1.0])}
    X = evidence_matrix(columns, ("b", "a"))
    assert X.tolist() == [[MISSING, 1.5], [2.0, MISSING]]
    with pytest.raises(KeyError, match="'d'"):
        evidence_matrix(columns, ("a", "d"))


def test_a_bad_model_file_is_named(tmp_path):
    bad = tmp_path / "model.json"
    bad.write_text(json.dumps({"features": ["a"], "base": 0, "learning_rate": 1, "trees": [_stump(3, 0, 0, 0)]}))
    with pytest.raises(ValueError, match="model.json"):
        load_kind_model(str(bad))
    with pytest.raises(FileNotFoundError, match="missing.json"):
        load_kind_model(str(tmp_path / "missing.json"))
    with pytest.raises(FileNotFoundError, match="degraded-image model.*missing.json"):
        load_degraded_model(str(tmp_path / "missing.json"))
    elsewhere = tmp_path / "other.json"
    elsewhere.write_text(ensemble_to_json(["not_measured"], 0.0, 1.0, [_stump(0, 0.0, 1.0, -1.0)], "motion",
                                          PROVENANCE))  # fmt: skip
    views = sharp_views()[:4]
    with pytest.raises(ValueError, match="kind-of-blur model .*other.json reads .*not_measured"):
        estimate_degradations(views + [motion_blur(views[0])], EstimateConfig(kind_model=str(elsewhere)))
    with pytest.raises(ValueError, match="degraded-image model .*other.json reads .*not_measured"):
        estimate_degradations(views + [motion_blur(views[0])], EstimateConfig(degraded_model=str(elsewhere)))


def test_a_model_file_rewritten_at_the_same_path_is_read_again(tmp_path):
    from gsmsdr_ns.io.atomic import write_text_atomic

    path = tmp_path / "kind.json"
    first = ensemble_to_json(["a"], 0.0, 1.0, [_stump(0, 0.0, -1.0, 1.0)], "motion", PROVENANCE)
    second = ensemble_to_json(["a"], 0.0, 1.0, [_stump(0, 0.0, 1.0, -1.0)], "motion", PROVENANCE)  # the opposite
    write_text_atomic(path, first)
    assert load_kind_model(str(path)).digest == parse_ensemble(first).digest
    assert load_kind_model(str(path)) is load_kind_model(str(path))  # unchanged: read once
    write_text_atomic(path, second)  # as fit_ensembles rewrites it, in the same process
    assert load_kind_model(str(path)).digest == parse_ensemble(second).digest
    assert probability(load_kind_model(str(path)), np.array([[1.0]]))[0] < 0.5


def test_the_builtin_models_read_the_estimate_evidence_and_key_the_cache():
    kind, degraded = load_kind_model(""), load_degraded_model("")
    assert kind.features == degraded.features == KIND_FEATURES and min(len(kind.trees), len(degraded.trees)) > 10
    assert kind.digest != degraded.digest
    assert estimate_fingerprint()["kind_model_digest"] == kind.digest
    assert estimate_fingerprint()["degraded_model_digest"] == degraded.digest
    rules = estimate_fingerprint(EstimateConfig(sharp_from="rules"))
    assert rules["kind_model_digest"] == kind.digest and "degraded_model_digest" not in rules
    # both record the settings of the evidence they read (the defaults), the sets they were fitted on
    for model in (kind, degraded):
        assert model.provenance["settings"] == PROVENANCE["settings"]
        assert model.provenance["fitting_sets"][:3] == ["A", "B", "C"] and len(model.provenance["fitting_sets"]) == 18


def _model_with(tmp_path: Path, provenance, name: str = "kind.json") -> Path:
    """A one-stump kind-of-blur model over the estimate's sharpness at tmp_path / name, with ``provenance`` (None:
    none)."""
    path = tmp_path / name
    path.write_text(ensemble_to_json(["sharpness"], 0.0, 1.0, [_stump(0, 0.5, 1.0, -1.0)], "motion", provenance))
    return path


def test_a_model_fitted_on_the_running_settings_loads(tmp_path):
    path = _model_with(tmp_path, PROVENANCE)
    assert load_kind_model(str(path)).provenance == PROVENANCE
    tuned = EstimateConfig(max_size=512)
    assert load_kind_model(str(_model_with(tmp_path, make_provenance(tuned, ["T"], "1.0"), "tuned.json")), tuned)
    # settings the evidence does not depend on may change
    load_kind_model(str(path), EstimateConfig(kind_probability=0.9, blurred_threshold=0.3, grid_threshold=20.0))


def test_a_model_fitted_on_other_settings_is_refused_naming_the_setting(tmp_path):
    path = _model_with(tmp_path, PROVENANCE)
    with pytest.raises(ValueError, match=r"kind\.json was fitted on evidence measured with max_size=1024, but the "
                                         r"estimate runs with max_size=512.*--config\.max-size 1024.*"
                                         r"tools\.estimate\.fit_ensembles"):  # fmt: skip
        load_kind_model(str(path), EstimateConfig(max_size=512))
    # the estimate checks the built-in files too: a sharp threshold moves the sharp images the detail spread is
    # relative to
    with pytest.raises(ValueError, match=r"kind-of-blur model .*kind_model\.json .*sharp_threshold=0\.6.*"
                                         r"sharp_threshold=0\.7"):  # fmt: skip
        estimate_degradations(sharp_views()[:4], EstimateConfig(sharp_threshold=0.7))


def test_a_model_without_provenance_is_refused(tmp_path):
    path = _model_with(tmp_path, None)
    with pytest.raises(ValueError, match=r"kind-of-blur model .*kind\.json records no provenance.*refit it with "
                                         r"python -m tools\.estimate\.fit_ensembles"):  # fmt: skip
        load_kind_model(str(path))
    unsettled = {k: v for k, v in PROVENANCE["settings"].items() if k != "coarse_sigma"}
    with pytest.raises(ValueError, match="does not record the setting coarse_sigma"):
        load_kind_model(str(_model_with(tmp_path, {**PROVENANCE, "settings": unsettled}, "unsettled.json")))


def test_stamping_provenance_leaves_the_trees_byte_for_byte(tmp_path):
    from tools.estimate.fit_ensembles import stamp_provenance

    path = _model_with(tmp_path, None)
    before = path.read_text()
    after = stamp_provenance(path, PROVENANCE)
    assert path.read_text() == after and load_kind_model(str(path)).provenance == PROVENANCE
    assert after.replace('"provenance":' + json.dumps(PROVENANCE, separators=(",", ":")) + ",", "") == before
    restamped = stamp_provenance(path, {**PROVENANCE, "fitting_sets": ["other"]})  # a block already there: replaced
    assert json.loads(restamped)["provenance"]["fitting_sets"] == ["other"] and restamped.count("provenance") == 1


def _evaluation_set(root: Path, offset: int) -> Path:
    """An evaluation set as tools.estimate.evaluate writes it: two scenes with true records (one shaken, one
    defocused), each of 4 sharp views, 4 blurred ones and 2 views defocused so mildly that the thresholds call them
    sharp."""
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
        for i in (0, 1):
            name = f"view_{i:02d}_soft.png"
            write_image(scene / "images" / name, defocus_by(views[i], 0.65 + 0.1 * i + 0.05 * offset))
            records[name] = {"degraded": True, "effects": {"defocus": {"radius_px": 0.7}}}
        (scene / "degradation.json").write_text(json.dumps({"version": 1, "images": records}), encoding="utf8")
    return root


@pytest.fixture(scope="module")
def evaluation_sets(tmp_path_factory) -> tuple[Path, Path]:
    """Two evaluation sets (see :func:`_evaluation_set`), written once for this module's tests (read only)."""
    root = tmp_path_factory.mktemp("sets")
    return _evaluation_set(root / "A", 0), _evaluation_set(root / "B", 1)


def test_the_fit_command_writes_ensembles_the_estimate_reads(evaluation_sets, tmp_path, capsys):
    import sklearn

    sets = evaluation_sets
    rows = collect_rows(sets)
    assert len(rows.truth) == 40 and set(rows.group) == {"A", "B"}
    kind, degraded = rows.kind_rows(), rows.degraded_rows()
    assert kind.sum() == 16 and (rows.truth[kind] == "motion").sum() == 8
    assert degraded.sum() == 24 and (rows.truth[degraded] != "sharp").sum() == 8  # the mild views pass as sharp
    out = tmp_path / "fitted"
    FitEnsemblesCLI(work=sets, kind_out=out / "kind.json", degraded_out=out / "degraded.json",
                    settings=FitSettings(trees=30, depth=2, learning_rate=0.3, subsample=1.0)).main()  # fmt: skip
    printed = capsys.readouterr().out
    assert "| all | generated | 16 |" in printed  # the leave-one-set-out tables: per set, then by threshold
    assert "| all | generated | 24 | 8 | 66.7 % |" in printed  # the thresholds alone call every one of these sharp
    sweep = [line for line in printed.splitlines() if line.startswith("| 0.")]
    kind_sweep = ["0.5", "0.55", "0.6", "0.65", "0.7", "0.75", "0.8"]
    degraded_sweep = ["0.5", "0.6", "0.7", "0.8", "0.9"]
    assert [line.split(" | ")[0][2:] for line in sweep] == kind_sweep + degraded_sweep
    assert sweep[0].endswith("| 0 / 0 |")  # at 0.5 every kind is named: none unknown
    assert sorted(p.name for p in out.iterdir()) == ["degraded.json", "kind.json"]  # no temporary file left behind
    for name in ("kind.json", "degraded.json"):
        provenance = json.loads((out / name).read_text())["provenance"]
        assert provenance["fitting_sets"] == ["A", "B"] and provenance["settings"] == PROVENANCE["settings"]
        assert provenance["scikit_learn"] == sklearn.__version__
    views = sharp_views()
    images = views[:4] + [motion_blur(views[4]), dwelling_shake(views[5], 10, 2.0), defocus_by(views[6], 3.0),
                          defocus_by(views[7], 3.5), defocus_by(views[2], 0.7), defocus_by(views[3], 0.75)]  # fmt: skip
    cfg = EstimateConfig(kind_model=str(out / "kind.json"), degraded_model=str(out / "degraded.json"))
    estimates = estimate_degradations(images, cfg)
    assert [e.label for e in estimates[:8]] == ["sharp"] * 4 + ["motion"] * 2 + ["defocus"] * 2
    assert all(e.motion_probability > 0.6 for e in estimates[4:6])
    assert all(e.motion_probability < 0.4 for e in estimates[6:8])
    assert all(e.motion_probability is None for e in estimates[:4])  # not blurred: not judged
    # the mild views: sharp by the thresholds, flagged by the ensemble, then of the kind the other one names
    assert all(e.degraded_probability >= 0.7 and e.blurred is None and e.label != "sharp" for e in estimates[8:])
    assert all(e.degraded_probability < 0.7 for e in estimates[:4])
    assert all(e.degraded_probability is None for e in estimates[4:8])  # not sharp by the thresholds: not asked
    rules = estimate_degradations(images, dataclasses.replace(cfg, sharp_from="rules"))
    assert [e.label for e in rules[8:]] == ["sharp", "sharp"]
    # a probability no image reaches leaves every kind unknown, the images still blurred
    unsure = estimate_degradations(images, dataclasses.replace(cfg, kind_probability=1.01))
    assert all(e.label == "unknown" and e.blurred is True for e in unsure[4:8])


def test_a_fit_on_closely_spaced_values_reproduces_scikit_learn_exactly():
    from sklearn.ensemble import GradientBoostingClassifier

    from tools.estimate.fit_ensembles import fit_ensemble

    rng = np.random.default_rng(0)
    X = 0.1 + rng.permutation(600)[:, None] * 3e-8 + np.zeros((1, 2))  # neighbours 3e-8 apart: below 7 decimals
    X[:, 1] = rng.random(600)
    y = X[:, 0] > 0.1 + 300 * 3e-8
    settings = FitSettings(trees=20)
    text = fit_ensemble(X, y, settings, "y", ("a", "b"))  # raises when it does not reproduce scikit-learn
    clf = GradientBoostingClassifier(n_estimators=20, max_depth=settings.depth, learning_rate=settings.learning_rate,
                                     subsample=settings.subsample, random_state=settings.seed).fit(X, y)  # fmt: skip
    assert np.abs(log_odds(parse_ensemble(text), X) - clf.decision_function(X)).max() < 1e-5


def test_the_fit_refuses_sets_without_both_kinds(evaluation_sets, tmp_path):
    root = tmp_path / "A"
    shutil.copytree(evaluation_sets[0] / "synth-motion", root / "synth-motion")  # shaken views only
    with pytest.raises(ValueError, match="all motion"):
        FitEnsemblesCLI(work=(root,), kind_out=tmp_path / "k.json", degraded_out=tmp_path / "d.json",
                        cross_validate=False).main()  # fmt: skip
    assert not (tmp_path / "k.json").exists() and not (tmp_path / "d.json").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="empty holds no scene"):
        collect_rows((tmp_path / "empty",))


def test_the_fit_trains_on_exactly_what_the_estimate_reads(evaluation_sets):
    from gsmsdr_ns.estimate.records import read_folder
    from tools.estimate.fit_ensembles import scene_rows

    scene = evaluation_sets[0] / "synth-motion"
    X, labels, truth = scene_rows(scene)
    names, images = read_folder(scene / "images")
    assert X.shape == (10, len(KIND_FEATURES)) and truth.count("motion") == 4 and truth.count("defocus") == 2
    estimates = estimate_degradations(images)
    # the same numbers through the built-in ensembles give the estimate's own probabilities
    judged = [i for i, e in enumerate(estimates) if e.motion_probability is not None]
    assert len(judged) >= 4
    assert np.allclose(probability(load_kind_model(""), X[judged]), [estimates[i].motion_probability for i in judged])
    asked = [i for i, e in enumerate(estimates) if e.degraded_probability is not None]
    assert asked == [i for i, label in enumerate(labels) if label == "sharp"] and len(asked) >= 4
    assert np.allclose(probability(load_degraded_model(""), X[asked]),
                       [estimates[i].degraded_probability for i in asked])  # fmt: skip


def test_the_degraded_image_ensemble_leaves_images_smaller_than_its_fitting_sets_to_the_thresholds():
    """It was fitted on images 200-600 px wide; on a set of 96x72 crops it is not asked, so labels are the
    thresholds' own."""
    from skimage.transform import resize

    views = sharp_views()
    small = [(resize(v, (72, 96), anti_aliasing=True) * 255).astype(np.uint8) for v in views]
    small += [(resize(defocus_by(v, 1.5), (72, 96), anti_aliasing=True) * 255).astype(np.uint8) for v in views[:2]]
    default = estimate_degradations(small)
    assert all(e.degraded_probability is None for e in default) and sum(e.label == "sharp" for e in default) >= 4
    rules = estimate_degradations(small, EstimateConfig(sharp_from="rules"))
    assert [e.label for e in default] == [e.label for e in rules]
    asked = estimate_degradations(small, EstimateConfig(degraded_min_size=0))
    assert [e.degraded_probability is not None for e in asked] == [e.label == "sharp" for e in default]
