"""Fit the kind-of-blur ensemble (:mod:`.kind_model`) on scenes whose records hold the truth, and cross-validate it.

    python -m gsmsdr_ns.estimate.fit_kind_model --work W/A W/B ... [--out kind_model.json]

Each ``--work`` folder is one evaluation set as :mod:`.evaluate` writes it (scenes with ``images/`` and a
``degradation.json`` of true records). Per scene, the estimate runs with the hand-set rules (``kind_from="rules"``);
every image it does not call sharp or mixres (blurred, or between sharp and blurred) whose truth is motion or
defocus alone is one training row: its evidence (:data:`~.kind_model.KIND_FEATURES`) and whether it is motion.
Gradient-boosted trees (scikit-learn) are fitted on all rows and written as JSON; before that, each set is scored
by the ensemble fitted on the other sets (leave one set out), which are the tables this prints: per set at the
estimate's probability threshold, and over all sets at several thresholds.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

import numpy as np
import tyro

from ..io.atomic import write_text_atomic
from ..io.images import read_image
from .classify import EstimateConfig, estimate_from_features
from .evaluate import truth_of
from .features import image_features
from .kind_model import BUILTIN_MODEL, KIND_FEATURES, ensemble_to_json, feature_matrix, log_odds, parse_ensemble


@dataclass
class TrainingRows:
    """Evidence rows of the blurred images of some sets."""

    X: np.ndarray
    """[n, len(KIND_FEATURES)] evidence (:func:`~.kind_model.feature_matrix`)."""
    motion: np.ndarray
    """[n] bool: the image is motion-blurred (else defocused)."""
    group: np.ndarray
    """[n] the set (work folder name) each row comes from."""
    synthetic: np.ndarray
    """[n] bool: the row comes from a generated scene (else from degraded photos)."""


def scene_rows(scene: Path) -> tuple[list[dict], list[bool]]:
    """(evidence per training image, is-motion per training image) of one scene with true records."""
    doc = json.loads((scene / "degradation.json").read_text(encoding="utf8"))
    names = sorted(doc["images"])
    feats = [image_features(read_image(scene / "images" / n)) for n in names]
    estimates = estimate_from_features(feats, EstimateConfig(kind_from="rules"))
    rows, motion = [], []
    for name, feat, est in zip(names, feats, estimates):
        truth, _ = truth_of(doc["images"][name])
        if truth not in ("motion", "defocus") or est.label in ("sharp", "mixres"):
            continue
        evidence = dataclasses.asdict(est)
        evidence.update(tile_coherence=feat.tile_coherence, spectral_anisotropy=feat.spectral_anisotropy)
        rows.append(evidence)
        motion.append(truth == "motion")
    return rows, motion


def collect_rows(work: Tuple[Path, ...]) -> TrainingRows:
    """The training rows of every scene (a folder with degradation.json) in each work folder."""
    X, y, group, synthetic = [], [], [], []
    for folder in work:
        scenes = sorted(p for p in Path(folder).iterdir() if (p / "degradation.json").is_file())
        if not scenes:
            raise FileNotFoundError(f"{folder} holds no scene with a degradation.json (write one with "
                                    "python -m gsmsdr_ns.estimate.evaluate --work ...)")  # fmt: skip
        for scene in scenes:
            rows, motion = scene_rows(scene)
            print(f"{folder}/{scene.name}: {len(rows)} blurred images", flush=True)
            if rows:
                X.append(feature_matrix(rows))
                y += motion
                group += [Path(folder).name] * len(rows)
                synthetic += [scene.name.startswith("synth")] * len(rows)
    if not X:
        raise ValueError("no motion- or defocus-blurred image in the given sets: nothing to fit")
    return TrainingRows(np.concatenate(X), np.array(y), np.array(group), np.array(synthetic))


@dataclass
class FitSettings:
    """Gradient boosting settings (scikit-learn's GradientBoostingClassifier)."""

    trees: int = 150
    """Boosting stages."""
    depth: int = 3
    """Depth of each tree."""
    learning_rate: float = 0.05
    """Shrinkage of each tree's output."""
    subsample: float = 0.7
    """Share of the rows each tree is fitted on."""
    seed: int = 0
    """Seed of the row subsampling."""


def fit_ensemble(X: np.ndarray, motion: np.ndarray, settings: FitSettings) -> str:
    """Fit on X [n, features] / motion [n] and return the ensemble's JSON text (:func:`~.kind_model.ensemble_to_json`),
    checked to reproduce scikit-learn's own decision function."""
    try:
        from sklearn.ensemble import GradientBoostingClassifier
    except ImportError as exc:  # pragma: no cover - scikit-learn comes with nerfstudio's dependencies
        raise ImportError("fitting the kind-of-blur model needs scikit-learn: pip install scikit-learn") from exc
    if len(set(motion.tolist())) < 2:
        raise ValueError("the training rows hold only one kind of blur: add sets with both motion and defocus")
    clf = GradientBoostingClassifier(n_estimators=settings.trees, max_depth=settings.depth,
                                     learning_rate=settings.learning_rate, subsample=settings.subsample,
                                     random_state=settings.seed).fit(X, motion)  # fmt: skip
    prior = float(np.mean(motion))
    trees = []
    for stage in clf.estimators_[:, 0]:
        t = stage.tree_
        trees.append({"left": t.children_left, "right": t.children_right, "feature": np.maximum(t.feature, 0),
                      "threshold": t.threshold, "value": t.value[:, 0, 0]})  # fmt: skip
    text = ensemble_to_json(KIND_FEATURES, np.log(prior / (1.0 - prior)), settings.learning_rate, trees)
    ours = log_odds(parse_ensemble(text), X)
    theirs = clf.decision_function(X)
    if not np.allclose(ours, theirs, atol=1e-3):
        raise RuntimeError(f"the exported ensemble differs from scikit-learn's by up to "
                           f"{np.abs(ours - theirs).max():.3g} in log-odds; not written")  # fmt: skip
    return text


def cross_validated_probability(rows: TrainingRows, settings: FitSettings) -> np.ndarray:
    """Leave one set out: each row's probability of motion from the ensemble fitted on the other sets -> [n]."""
    groups = list(dict.fromkeys(rows.group.tolist()))
    if len(groups) < 2:
        raise ValueError("cross-validation needs at least two sets")
    p = np.zeros(len(rows.motion))
    for g in groups:
        held = rows.group == g
        model = parse_ensemble(fit_ensemble(rows.X[~held], rows.motion[~held], settings))
        p[held] = 1.0 / (1.0 + np.exp(-log_odds(model, rows.X[held])))
    return p


def _counts(p: np.ndarray, motion: np.ndarray, probability: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, wrong, unknown) [n] bool of probabilities p [n] against the truth at a probability threshold."""
    decided = np.maximum(p, 1.0 - p) >= probability
    return decided & ((p >= 0.5) == motion), decided & ((p >= 0.5) != motion), ~decided


def cross_validation_tables(rows: TrainingRows, p: np.ndarray, probability: float, sweep: Tuple[float, ...]) -> str:
    """Markdown: per set and kind of scene, right / wrong / unknown kinds at ``probability``; then, over all rows,
    the same at each threshold of ``sweep`` (what a threshold trades: wrong kinds against unknown ones)."""
    right, wrong, unknown = _counts(p, rows.motion, probability)
    lines = [f"Leave one set out, probability {probability}:", "",
             "| set | scenes | blurred images | right | wrong kind | unknown |", "|---|---|---|---|---|---|"]  # fmt: skip
    for g in list(dict.fromkeys(rows.group.tolist())) + ["all"]:
        for synthetic, kind in ((True, "generated"), (False, "photos")):
            k = (rows.synthetic == synthetic) & ((rows.group == g) if g != "all" else True)
            if k.sum():
                lines.append(f"| {g} | {kind} | {int(k.sum())} | {100 * right[k].mean():.1f} % | {int(wrong[k].sum())} "
                             f"| {int(unknown[k].sum())} |")  # fmt: skip
    lines += ["", "Leave one set out, all sets, by threshold (generated / photos):", "",
              "| probability | right | wrong kind | unknown |", "|---|---|---|---|"]  # fmt: skip
    gen = rows.synthetic
    for t in sweep:
        r, w, u = _counts(p, rows.motion, t)
        lines.append(f"| {t} | {100 * r[gen].mean():.1f} % / {100 * r[~gen].mean():.1f} % | {int(w[gen].sum())} / "
                     f"{int(w[~gen].sum())} | {int(u[gen].sum())} / {int(u[~gen].sum())} |")  # fmt: skip
    return "\n".join(lines)


@dataclass
class FitKindModelCLI:
    """Fit the degradation estimate's kind-of-blur ensemble on evaluation sets with true records."""

    work: Tuple[Path, ...]
    """Evaluation sets (folders written by python -m gsmsdr_ns.estimate.evaluate --work ...)."""
    out: Path = BUILTIN_MODEL
    """Where the ensemble's JSON goes (default: the one the package ships)."""
    settings: FitSettings = dataclasses.field(default_factory=FitSettings)
    """Boosting settings."""
    cross_validate: bool = True
    """Print the leave-one-set-out table first."""
    probability: float = EstimateConfig.kind_probability
    """Probability from which the table counts a kind as named (EstimateConfig.kind_probability)."""
    sweep: Tuple[float, ...] = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8)
    """Thresholds of the second table (right / wrong / unknown kinds at each)."""

    def main(self) -> List[str]:
        rows = collect_rows(self.work)
        print(f"{len(rows.motion)} rows: {int(rows.motion.sum())} motion, {int((~rows.motion).sum())} defocus")
        if self.cross_validate:
            p = cross_validated_probability(rows, self.settings)
            print(cross_validation_tables(rows, p, self.probability, self.sweep))
        write_text_atomic(self.out, fit_ensemble(rows.X, rows.motion, self.settings))
        print(f"wrote {self.out}")
        return [str(self.out)]


if __name__ == "__main__":
    tyro.cli(FitKindModelCLI).main()
