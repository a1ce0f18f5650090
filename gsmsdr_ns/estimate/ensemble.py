"""Fitted tree ensembles over an image's evidence: is a sharp-looking image degraded, and is a blurred one
motion- or defocus-blurred.

Each number of the evidence (:mod:`.evidence`) sees one trait of a blur; together they decide much better than any
rule chain we set by hand. Two ensembles are fitted by ``python -m tools.estimate.fit_ensembles`` (in the
repository, not the package) on scenes whose records hold the truth (results in docs/results/estimate/results.md)
and stored as JSON beside this module: ``kind_model.json`` (log-odds of motion against defocus) and
``degraded_model.json`` (log-odds that an image the thresholds call sharp is degraded). Both are boosted regression
trees evaluated here with numpy.

Each file records its provenance: the settings its input numbers were measured with
(:data:`~.config.EVIDENCE_SETTINGS`), the sets it was fitted on and the scikit-learn version. The loaders refuse a
file whose settings differ from the running config's, or that records none: its trees would read numbers that mean
something else.

Pure functions over arrays; the only state is the loaded models (immutable values).
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

import numpy as np

from .config import EstimateConfig, evidence_settings

KIND_FEATURES = (
    "anisotropy",
    "width_spread",
    "isotropy",
    "sharpest_region",
    "directional_loss",
    "detail_spread",
    "edge_rise",
    "tile_coherence",
    "spectral_anisotropy",
    "sharpness",
    "soft_width",
    "edge_sharpness",
    "laplacian_variance",
)
"""The evidence the ensembles read, in column order: the names of :class:`~.evidence.SetEvidence`'s arrays."""

MISSING = -1.0
"""The value of a missing number (NaN, None) in the feature matrix: every feature is >= 0 when measured, so the
trees can route "not measured" on its own."""

BUILTIN_KIND_MODEL = Path(__file__).with_name("kind_model.json")
"""The kind-of-blur ensemble shipped with the package (log-odds of motion)."""
BUILTIN_DEGRADED_MODEL = Path(__file__).with_name("degraded_model.json")
"""The ensemble shipped with the package that flags images the thresholds call sharp (log-odds of degraded)."""


@dataclass(frozen=True)
class TreeEnsemble:
    """Boosted binary regression trees. Node arrays per tree, all [nodes]: ``left`` / ``right`` child index (-1 at
    a leaf), ``feature`` column, ``threshold`` (go left when value <= threshold), ``value`` (leaf output)."""

    features: tuple
    """Column names (:data:`KIND_FEATURES` when fitted by this project)."""
    base: float
    """Log-odds before any tree."""
    learning_rate: float
    """Factor on every tree's output."""
    trees: tuple
    """One (left, right, feature, threshold, value) tuple of arrays per tree."""
    digest: str
    """sha256 of the JSON it was read from (cache keys)."""
    provenance: Optional[Mapping] = field(default=None, compare=False)
    """The file's provenance block (:func:`make_provenance`); None when it records none."""


def make_provenance(config: EstimateConfig, fitting_sets: Sequence[str], scikit_learn: str) -> Dict[str, Any]:
    """The provenance block of an ensemble fitted on evidence measured with ``config``: {"settings": the values of
    :data:`~.config.EVIDENCE_SETTINGS`, "fitting_sets": the sets' names, "scikit_learn": the fitting library's
    version}."""
    return {"settings": evidence_settings(config), "fitting_sets": list(fitting_sets), "scikit_learn": scikit_learn}


def ensemble_to_json(
    features: Sequence[str],
    base: float,
    learning_rate: float,
    trees: Sequence[Mapping],
    target: str,
    provenance: Optional[Mapping] = None,
) -> str:
    """The JSON text of an ensemble; each tree a mapping of the node lists left, right, feature, threshold, value;
    ``target``: what its log-odds are of (for the reader); ``provenance``: its :func:`make_provenance` block (None:
    none, which the loaders refuse)."""
    doc = {
        "kind": f"gradient-boosted trees, log-odds of {target}",
        "features": list(features),
        "missing": MISSING,
        "base": float(base),
        "learning_rate": float(learning_rate),
        **({"provenance": dict(provenance)} if provenance is not None else {}),
        # thresholds exact (a rounded one can move past a measured value), leaf values rounded
        "trees": [
            {
                k: [float(v) if k == "threshold" else round(float(v), 7) if k == "value" else int(v) for v in t[k]]
                for k in ("left", "right", "feature", "threshold", "value")
            }
            for t in trees
        ],  # fmt: skip
    }
    return json.dumps(doc, separators=(",", ":"))


def parse_ensemble(text: str, source: str = "<text>") -> TreeEnsemble:
    """A :class:`TreeEnsemble` from :func:`ensemble_to_json` text; ValueError naming ``source`` when malformed."""
    try:
        doc = json.loads(text)
        features = tuple(doc["features"])
        trees = []
        for t in doc["trees"]:
            arrays = (np.asarray(t["left"], np.int64), np.asarray(t["right"], np.int64),
                      np.asarray(t["feature"], np.int64), np.asarray(t["threshold"], np.float64),
                      np.asarray(t["value"], np.float64))  # fmt: skip
            n = len(arrays[0])
            if n == 0 or any(len(a) != n for a in arrays) or arrays[2].max() >= len(features):
                raise ValueError("node arrays of unequal length or a feature index out of range")
            trees.append(arrays)
        provenance = doc.get("provenance")
        if provenance is not None and not isinstance(provenance.get("settings"), dict):
            raise ValueError("its provenance block has no settings")
        model = TreeEnsemble(features, float(doc["base"]), float(doc["learning_rate"]), tuple(trees),
                             hashlib.sha256(text.encode("utf8")).hexdigest(), provenance)  # fmt: skip
    except (KeyError, TypeError, AttributeError, ValueError, json.JSONDecodeError) as exc:
        raise ValueError(f"{source} is not an ensemble written by python -m tools.estimate.fit_ensembles "
                         f"({exc}); refit it or remove the path to use the built-in one") from exc  # fmt: skip
    return model


@functools.lru_cache(maxsize=8)
def _parse_file(file: Path, inode: int, mtime_ns: int, size: int) -> TreeEnsemble:
    """The ensemble in ``file`` as it was at (inode, mtime_ns, size): a file replaced or rewritten is read again."""
    return parse_ensemble(file.read_text(encoding="utf8"), str(file))


REFIT = "python -m tools.estimate.fit_ensembles"
"""The command that fits both ensembles, run from the repository root (named in the loaders' errors)."""


def check_provenance(model: TreeEnsemble, config: EstimateConfig, source: str) -> None:
    """ValueError naming ``source`` when the model records no provenance, or when a setting its input numbers were
    measured with (:data:`~.config.EVIDENCE_SETTINGS`) differs from ``config``'s: the setting, both values and the
    two ways out."""
    if model.provenance is None:
        raise ValueError(f"{source} records no provenance (the settings its evidence was measured with), so the "
                         f"estimate cannot tell whether it reads the numbers it was fitted on; refit it with "
                         f"{REFIT} (from the repository root)")  # fmt: skip
    recorded = model.provenance["settings"]
    for name, value in evidence_settings(config).items():
        if name not in recorded:
            raise ValueError(f"{source} does not record the setting {name} its evidence depends on; refit it with "
                             f"{REFIT} (from the repository root)")  # fmt: skip
        if recorded[name] != value:
            flag = "--config." + name.replace("_", "-")
            raise ValueError(f"{source} was fitted on evidence measured with {name}={recorded[name]!r}, but the "
                             f"estimate runs with {name}={value!r}: its trees would read numbers that mean "
                             f"something else. Either use {name}={recorded[name]!r} (gsmsdr-estimate: {flag} "
                             f"{recorded[name]}), or refit both ensembles (from the repository root: {REFIT} "
                             f"--work ... {flag} {value} --kind-out K.json --degraded-out D.json) and set "
                             f"kind_model and degraded_model to them")  # fmt: skip


def _load(path: str, builtin: Path, what: str, config: Optional[EstimateConfig]) -> TreeEnsemble:
    file = Path(path) if path else builtin
    if not file.is_file():
        raise FileNotFoundError(f"{what} {file} not found; use '' for the built-in one or write one with "
                                f"{REFIT} (from the repository root)")  # fmt: skip
    stat = file.stat()
    model = _parse_file(file, stat.st_ino, stat.st_mtime_ns, stat.st_size)
    check_provenance(model, config or EstimateConfig(), f"{what} {file}")
    return model


def load_kind_model(path: str = "", config: Optional[EstimateConfig] = None) -> TreeEnsemble:
    """The kind-of-blur ensemble at ``path`` ("": the built-in one), read again only when the file changed; checked
    against ``config`` (default: the default config) by :func:`check_provenance`."""
    return _load(path, BUILTIN_KIND_MODEL, "kind-of-blur model (EstimateConfig.kind_model)", config)


def load_degraded_model(path: str = "", config: Optional[EstimateConfig] = None) -> TreeEnsemble:
    """The degraded-image ensemble at ``path`` ("": the built-in one), read again only when the file changed;
    checked against ``config`` as :func:`load_kind_model`."""
    return _load(path, BUILTIN_DEGRADED_MODEL, "degraded-image model (EstimateConfig.degraded_model)", config)


def evidence_matrix(columns: Mapping[str, np.ndarray], features: Sequence[str] = KIND_FEATURES) -> np.ndarray:
    """[n, len(features)] from one array [n] per evidence name; NaN / inf become :data:`MISSING`. KeyError naming
    the features ``columns`` lacks."""
    missing = [f for f in features if f not in columns]
    if missing:
        raise KeyError(f"no evidence named {missing} (measured: {', '.join(columns)})")
    X = np.stack([np.asarray(columns[f], np.float64) for f in features], axis=1)
    return np.where(np.isfinite(X), X, MISSING)


def log_odds(model: TreeEnsemble, X: np.ndarray) -> np.ndarray:
    """Log-odds per row of X [n, features] -> [n]. X is compared in float32, as scikit-learn fits and evaluates its
    trees."""
    X = np.asarray(X, dtype=np.float32)
    total = np.full(len(X), model.base)
    rows = np.arange(len(X))
    for left, right, feature, threshold, value in model.trees:
        node = np.zeros(len(X), np.int64)
        while True:
            inner = left[node] >= 0
            if not inner.any():
                break
            go_left = X[rows, feature[node]] <= threshold[node]
            node = np.where(inner, np.where(go_left, left[node], right[node]), node)
        total += model.learning_rate * value[node]
    return total


def probability(model: TreeEnsemble, X: np.ndarray) -> np.ndarray:
    """The ensemble's probability per row of X [n, features] -> [n]."""
    return 1.0 / (1.0 + np.exp(-log_odds(model, X)))


__all__ = [
    "KIND_FEATURES",
    "MISSING",
    "BUILTIN_KIND_MODEL",
    "BUILTIN_DEGRADED_MODEL",
    "TreeEnsemble",
    "make_provenance",
    "check_provenance",
    "ensemble_to_json",
    "parse_ensemble",
    "load_kind_model",
    "load_degraded_model",
    "evidence_matrix",
    "log_odds",
    "probability",
]
