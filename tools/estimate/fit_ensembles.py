"""Fit the estimate's two ensembles (:mod:`gsmsdr_ns.estimate.ensemble`) on scenes whose records hold the truth,
and cross-validate them. Run from the repository root (needs scikit-learn)::

    python -m tools.estimate.fit_ensembles --work W/A W/B ... [--kind-out K.json] [--degraded-out D.json]

Each ``--work`` folder is one evaluation set as :mod:`.evaluate` writes it (scenes with ``images/`` and a
``degradation.json`` of true records). Per scene, the estimate's evidence
(:class:`~gsmsdr_ns.estimate.evidence.SetEvidence`, measured with ``--config``) and what its thresholds alone make
of each image (:func:`~gsmsdr_ns.estimate.classify.threshold_stages`) are computed; one row per image.

* **kind of blur**: the images the thresholds do not call sharp or mixres whose truth is motion or defocus alone;
  target: motion.
* **degraded**: the images the thresholds call sharp whose truth is sharp, motion or defocus; target: degraded.

Gradient-boosted trees (scikit-learn) are fitted on all rows of each and written as JSON with their provenance (the
config's :data:`~gsmsdr_ns.estimate.config.EVIDENCE_SETTINGS`, the sets' folder names, the scikit-learn version),
which the estimate checks when it loads them; before that, each set is scored by the ensembles fitted on the other
sets (leave one set out): per set at the estimate's probability thresholds, and over all sets at several
thresholds. :func:`stamp_provenance` adds the block to a file fitted before provenance was recorded.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, List, Mapping, Optional, Tuple

import numpy as np
import tyro

from gsmsdr_ns.estimate.classify import threshold_stages
from gsmsdr_ns.estimate.config import EstimateConfig
from gsmsdr_ns.estimate.ensemble import (
    BUILTIN_DEGRADED_MODEL,
    BUILTIN_KIND_MODEL,
    KIND_FEATURES,
    ensemble_to_json,
    evidence_matrix,
    log_odds,
    make_provenance,
    parse_ensemble,
    probability,
)
from gsmsdr_ns.estimate.evidence import measure_images, set_evidence
from gsmsdr_ns.io.atomic import write_text_atomic
from gsmsdr_ns.io.images import read_image
from tools.estimate.evaluate import truth_of


@dataclass
class EvidenceRows:
    """One row per image of some sets: its evidence, what the thresholds make of it and the truth."""

    X: np.ndarray
    """[n, len(KIND_FEATURES)] evidence (:func:`~gsmsdr_ns.estimate.ensemble.evidence_matrix`)."""
    truth: np.ndarray
    """[n] the records' label (:func:`~.evaluate.truth_of`: sharp, motion, defocus, mixres or a '+' list)."""
    stages: np.ndarray
    """[n] what the thresholds alone make of the image (:func:`~gsmsdr_ns.estimate.classify.threshold_stages`)."""
    group: np.ndarray
    """[n] the set (work folder name) each row comes from."""
    synthetic: np.ndarray
    """[n] bool: the row comes from a generated scene (else from degraded photos)."""

    def kind_rows(self) -> np.ndarray:
        """[n] bool: the rows the kind-of-blur ensemble is fitted on."""
        return ~np.isin(self.stages, ["sharp", "mixres"]) & np.isin(self.truth, ["motion", "defocus"])

    def degraded_rows(self) -> np.ndarray:
        """[n] bool: the rows the degraded-image ensemble is fitted on."""
        return (self.stages == "sharp") & np.isin(self.truth, ["sharp", "motion", "defocus"])


def scene_rows(scene: Path, config: Optional[EstimateConfig] = None) -> tuple[np.ndarray, list[str], list[str]]:
    """(evidence [n, features], threshold stage per image, true label per image) of one scene with true records,
    measured with ``config`` (default: the default config)."""
    doc = json.loads((scene / "degradation.json").read_text(encoding="utf8"))
    names = sorted(doc["images"])
    ev = set_evidence(measure_images([read_image(scene / "images" / n) for n in names], config), config)
    return evidence_matrix(ev.columns()), threshold_stages(ev, config), [truth_of(doc["images"][n])[0] for n in names]


def collect_rows(work: Tuple[Path, ...], config: Optional[EstimateConfig] = None) -> EvidenceRows:
    """The rows of every scene (a folder with degradation.json) in each work folder, measured with ``config``."""
    X, truth, stages, group, synthetic = [], [], [], [], []
    for folder in work:
        scenes = sorted(p for p in Path(folder).iterdir() if (p / "degradation.json").is_file())
        if not scenes:
            raise FileNotFoundError(f"{folder} holds no scene with a degradation.json (write one with "
                                    "python -m tools.estimate.evaluate --work ...)")  # fmt: skip
        for scene in scenes:
            x, scene_stages, truths = scene_rows(scene, config)
            print(f"{folder}/{scene.name}: {len(truths)} images", flush=True)
            X.append(x)
            stages += scene_stages
            truth += truths
            group += [Path(folder).name] * len(truths)
            synthetic += [scene.name.startswith("synth")] * len(truths)
    return EvidenceRows(np.concatenate(X), np.array(truth), np.array(stages), np.array(group), np.array(synthetic))


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


def _scikit_learn():
    """The sklearn module; ImportError saying how to install it."""
    try:
        import sklearn
        import sklearn.ensemble
    except ImportError as exc:  # pragma: no cover - a test dependency (pyproject's [test] extra)
        raise ImportError("fitting the estimate's ensembles needs scikit-learn: pip install scikit-learn") from exc
    return sklearn


def fit_ensemble(
    X: np.ndarray,
    y: np.ndarray,
    settings: FitSettings,
    target: str,
    features: Tuple[str, ...] = KIND_FEATURES,
    provenance: Optional[Mapping] = None,
) -> str:
    """Fit on X [n, len(features)] / y [n] bool and return the ensemble's JSON text
    (:func:`~gsmsdr_ns.estimate.ensemble.ensemble_to_json`; ``features`` names X's columns, ``target`` what y is,
    ``provenance`` goes into the file), checked to reproduce scikit-learn's own decision function."""
    GradientBoostingClassifier = _scikit_learn().ensemble.GradientBoostingClassifier
    if len(set(y.tolist())) < 2:
        raise ValueError(f"the training rows are all {'' if y.all() else 'not '}{target}: add sets with both")
    clf = GradientBoostingClassifier(n_estimators=settings.trees, max_depth=settings.depth,
                                     learning_rate=settings.learning_rate, subsample=settings.subsample,
                                     random_state=settings.seed).fit(X, y)  # fmt: skip
    prior = float(np.mean(y))
    trees = []
    for stage in clf.estimators_[:, 0]:
        t = stage.tree_
        trees.append({"left": t.children_left, "right": t.children_right, "feature": np.maximum(t.feature, 0),
                      "threshold": t.threshold, "value": t.value[:, 0, 0]})  # fmt: skip
    text = ensemble_to_json(features, np.log(prior / (1.0 - prior)), settings.learning_rate, trees, target,
                            provenance)  # fmt: skip
    ours = log_odds(parse_ensemble(text), X)
    theirs = clf.decision_function(X)
    if not np.allclose(ours, theirs, atol=1e-3):
        raise RuntimeError(f"the exported ensemble differs from scikit-learn's by up to "
                           f"{np.abs(ours - theirs).max():.3g} in log-odds; not written")  # fmt: skip
    return text


def cross_validated_probability(X: np.ndarray, y: np.ndarray, group: np.ndarray, settings: FitSettings) -> np.ndarray:
    """Leave one set out: each row's probability from the ensemble fitted on the other sets' rows -> [n]."""
    groups = list(dict.fromkeys(group.tolist()))
    if len(groups) < 2:
        raise ValueError("cross-validation needs at least two sets")
    p = np.zeros(len(y))
    for g in groups:
        held = group == g
        p[held] = probability(parse_ensemble(fit_ensemble(X[~held], y[~held], settings, "y")), X[held])
    return p


def _counts(p: np.ndarray, motion: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, wrong, unknown) [n] bool of probabilities of motion p [n] against the truth at a threshold."""
    decided = np.maximum(p, 1.0 - p) >= threshold
    return decided & ((p >= 0.5) == motion), decided & ((p >= 0.5) != motion), ~decided


def kind_tables(rows: EvidenceRows, p: np.ndarray, threshold: float, sweep: Tuple[float, ...]) -> str:
    """Markdown, kind-of-blur rows and their cross-validated probabilities of motion p: per set and kind of scene,
    right / wrong / unknown kinds at ``threshold``; then, over all rows, the same at each threshold of ``sweep``."""
    k = rows.kind_rows()
    motion, group, synth = rows.truth[k] == "motion", rows.group[k], rows.synthetic[k]
    right, wrong, unknown = _counts(p, motion, threshold)
    lines = [f"Kind of blur, leave one set out, probability {threshold}:", "",
             "| set | scenes | blurred images | right | wrong kind | unknown |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for g, kind, m in _per_set(group, synth):
        lines.append(f"| {g} | {kind} | {int(m.sum())} | {100 * right[m].mean():.1f} % | {int(wrong[m].sum())} "
                     f"| {int(unknown[m].sum())} |")  # fmt: skip
    lines += ["", "Kind of blur, leave one set out, all sets, by threshold (generated / photos):", "",
              "| probability | right | wrong kind | unknown |", "|---|---|---|---|"]  # fmt: skip
    for t in sweep:
        r, w, u = _counts(p, motion, t)
        lines.append(f"| {t} | {_share(r, synth)} | {_sum(w, synth)} | {_sum(u, synth)} |")
    return "\n".join(lines)


def degraded_tables(rows: EvidenceRows, p: np.ndarray, threshold: float, sweep: Tuple[float, ...]) -> str:
    """Markdown, degraded-image rows and their cross-validated probabilities of degraded p: per set and kind of
    scene, the sharp-vs-degraded accuracy of these rows by the thresholds alone and with the ensemble's flag at
    ``threshold`` (degraded images caught, sharp ones lost); then, over all rows, the same at each of ``sweep``."""
    k = rows.degraded_rows()
    degraded, group, synth = rows.truth[k] != "sharp", rows.group[k], rows.synthetic[k]
    lines = [f"Images the thresholds call sharp, leave one set out, probability {threshold}:", "",
             "| set | scenes | images | degraded | right, thresholds | right, flagged | caught | sharp lost |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    flagged = p >= threshold
    for g, kind, m in _per_set(group, synth):
        caught, lost = (flagged & degraded)[m].sum(), (flagged & ~degraded)[m].sum()
        lines.append(f"| {g} | {kind} | {int(m.sum())} | {int(degraded[m].sum())} | "
                     f"{100 * (~degraded[m]).mean():.1f} % | {100 * (flagged == degraded)[m].mean():.1f} % | "
                     f"{int(caught)} | {int(lost)} |")  # fmt: skip
    lines += ["", "Images the thresholds call sharp, all sets, by threshold (generated / photos):", "",
              "| probability | right | caught | sharp lost |", "|---|---|---|---|"]  # fmt: skip
    for t in sweep:
        f = p >= t
        lines.append(f"| {t} | {_share(f == degraded, synth)} | {_sum(f & degraded, synth)} | "
                     f"{_sum(f & ~degraded, synth)} |")  # fmt: skip
    return "\n".join(lines)


def stamp_provenance(path: Path, provenance: Mapping) -> str:
    """Write ``provenance`` (:func:`~gsmsdr_ns.estimate.ensemble.make_provenance`) into the ensemble JSON at
    ``path``, before its trees (replacing a block already there) -> the new text. Nothing else changes: a file
    without a block must be in :func:`~gsmsdr_ns.estimate.ensemble.ensemble_to_json`'s form, so that the new text
    is the old one with the block inserted, and the trees must read back identical; RuntimeError, nothing written,
    otherwise."""
    text = Path(path).read_text(encoding="utf8")
    doc = json.loads(text)
    if "provenance" not in doc and json.dumps(doc, separators=(",", ":")) != text:
        raise RuntimeError(f"{path} is not in the form the fit writes; refit it instead of stamping it")
    stamped = {k: v for k, v in doc.items() if k not in ("provenance", "trees")}
    stamped["provenance"] = dict(provenance)
    stamped["trees"] = doc["trees"]
    new = json.dumps(stamped, separators=(",", ":"))
    old, ours = parse_ensemble(text, str(path)), parse_ensemble(new, str(path))
    same = (old.features, old.base, old.learning_rate, len(old.trees)) == (
        ours.features, ours.base, ours.learning_rate, len(ours.trees))  # fmt: skip
    if not same or not all(np.array_equal(a, b) for t, u in zip(old.trees, ours.trees) for a, b in zip(t, u)):
        raise RuntimeError(f"stamping {path} would change its trees; not written")
    write_text_atomic(path, new)
    return new


def _per_set(group: np.ndarray, synth: np.ndarray) -> Iterator[tuple[str, str, np.ndarray]]:
    """(set, "generated" / "photos", row mask [n]) for each set in order, then "all", skipping empty masks."""
    for g in list(dict.fromkeys(group.tolist())) + ["all"]:
        for synthetic, kind in ((True, "generated"), (False, "photos")):
            m = (synth == synthetic) & ((group == g) if g != "all" else True)
            if m.sum():
                yield g, kind, m


def _share(ok: np.ndarray, synth: np.ndarray) -> str:
    """'generated % / photos %' of a bool array ('-' for a side without rows)."""
    return " / ".join(f"{100 * ok[m].mean():.1f} %" if m.any() else "-" for m in (synth, ~synth))


def _sum(flag: np.ndarray, synth: np.ndarray) -> str:
    """'generated / photos' counts of a bool array."""
    return f"{int(flag[synth].sum())} / {int(flag[~synth].sum())}"


@dataclass
class FitEnsemblesCLI:
    """Fit the degradation estimate's two ensembles on evaluation sets with true records."""

    work: Tuple[Path, ...]
    """Evaluation sets (folders written by python -m tools.estimate.evaluate --work ...); their folder names are
    recorded as the fitting sets."""
    kind_out: Path = BUILTIN_KIND_MODEL
    """Where the kind-of-blur ensemble's JSON goes (default: the one the package ships)."""
    degraded_out: Path = BUILTIN_DEGRADED_MODEL
    """Where the degraded-image ensemble's JSON goes (default: the one the package ships)."""
    settings: FitSettings = dataclasses.field(default_factory=FitSettings)
    """Boosting settings (both ensembles)."""
    config: EstimateConfig = dataclasses.field(default_factory=EstimateConfig)
    """The estimate settings the evidence is measured with (and the rows chosen by); the ones the evidence depends
    on are recorded in both files, and the estimate reads them only under the same values."""
    cross_validate: bool = True
    """Print the leave-one-set-out tables first."""
    kind_probability: float = EstimateConfig.kind_probability
    """Probability from which the kind table counts a kind as named (EstimateConfig.kind_probability)."""
    degraded_probability: float = EstimateConfig.degraded_probability
    """Probability from which the degraded table counts an image as flagged (EstimateConfig.degraded_probability)."""
    kind_sweep: Tuple[float, ...] = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8)
    """Thresholds of the kind table's sweep."""
    degraded_sweep: Tuple[float, ...] = (0.5, 0.6, 0.7, 0.8, 0.9)
    """Thresholds of the degraded table's sweep."""

    def main(self) -> List[str]:
        rows = collect_rows(self.work, self.config)
        provenance = make_provenance(self.config, [Path(w).name for w in self.work], _scikit_learn().__version__)
        jobs = []
        for name, mask, y, target, out, threshold, sweep, tables in (
            ("kind of blur", rows.kind_rows(), rows.truth == "motion", "motion", self.kind_out,
             self.kind_probability, self.kind_sweep, kind_tables),
            ("degraded", rows.degraded_rows(), rows.truth != "sharp", "degraded", self.degraded_out,
             self.degraded_probability, self.degraded_sweep, degraded_tables),
        ):  # fmt: skip
            X, y = rows.X[mask], y[mask]
            print(f"{name}: {len(y)} rows, {int(y.sum())} {target}")
            if self.cross_validate:
                p = cross_validated_probability(X, y, rows.group[mask], self.settings)
                print(tables(rows, p, threshold, sweep))
            jobs.append((out, fit_ensemble(X, y, self.settings, target, provenance=provenance)))
        for out, text in jobs:  # both fitted before either is written
            write_text_atomic(out, text)
            print(f"wrote {out}")
        return [str(out) for out, _ in jobs]


if __name__ == "__main__":
    tyro.cli(FitEnsemblesCLI).main()
