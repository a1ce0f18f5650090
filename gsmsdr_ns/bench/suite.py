"""`gsmsdr-bench suite`: benchmark suites from ``configs/bench/*.yaml`` (scenes x methods x step budgets x seeds).

The suite's parts, one job per module:

* :mod:`gsmsdr_ns.bench.suite_config`: suite YAML -> :class:`Suite` (validation naming the file and the key),
  :func:`find_suite_file` (packaged ``configs/bench/`` names);
* :mod:`gsmsdr_ns.bench.methods`: the one method registry :data:`METHODS` (plain, full, view, gsmsdr-lite, sharp,
  msd-only, re-only, -gaka, -safm, -mca, -rgbd, -view);
* :mod:`gsmsdr_ns.bench.scenes`: generated scenes; :mod:`gsmsdr_ns.bench.training`: in-process training with one
  :class:`gsmsdr_ns.plugin.schedule.TrainingSchedule`; :mod:`gsmsdr_ns.bench.evaluation`: the one evaluation
  definition (PSNR, scikit-image SSIM, LPIPS when cached);
* :mod:`gsmsdr_ns.bench.runner`: running a suite in this process; :mod:`gsmsdr_ns.bench.ray_runner`: on a Ray
  cluster; :mod:`gsmsdr_ns.bench.ledger`: what both record (the plan, resuming, records and outputs after each
  run); :mod:`gsmsdr_ns.bench.records`: the run records (writing, loading, collecting those that match);
  :mod:`gsmsdr_ns.bench.fingerprint`: what a record depends on;
* :mod:`gsmsdr_ns.bench.report`: results.csv, results.md, plots (:mod:`gsmsdr_ns.bench.plots`), publishing them into
  ``docs/results/<suite>/``.

This module gathers their public names.
"""

from __future__ import annotations

from gsmsdr_ns.bench.evaluation import evaluate_test_views, make_lpips
from gsmsdr_ns.bench.fingerprint import fingerprint
from gsmsdr_ns.bench.ledger import SuiteOutcome
from gsmsdr_ns.bench.methods import METHODS, MethodSpec
from gsmsdr_ns.bench.records import collect_records, finished_record, record_path
from gsmsdr_ns.bench.report import format_markdown, main_tables, publish_outputs, write_outputs
from gsmsdr_ns.bench.runner import run_suite, train_and_record
from gsmsdr_ns.bench.suite_config import RunKey, SceneEntry, Suite, SuiteConfigError, find_suite_file, load_suite

__all__ = [
    "METHODS",
    "MethodSpec",
    "RunKey",
    "SceneEntry",
    "Suite",
    "SuiteConfigError",
    "SuiteOutcome",
    "collect_records",
    "evaluate_test_views",
    "find_suite_file",
    "fingerprint",
    "finished_record",
    "format_markdown",
    "load_suite",
    "make_lpips",
    "main_tables",
    "publish_outputs",
    "record_path",
    "run_suite",
    "train_and_record",
    "write_outputs",
]
