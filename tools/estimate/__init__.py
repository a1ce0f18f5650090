"""The degradation estimate's research tools: scoring it on scenes with true records (:mod:`.evaluate`) and fitting
its ensembles on them (:mod:`.fit_ensembles`, needs scikit-learn). Run from the repository root, e.g.
``python -m tools.estimate.evaluate`` and ``python -m tools.estimate.fit_ensembles --work ...``."""
