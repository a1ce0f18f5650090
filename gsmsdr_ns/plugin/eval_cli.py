"""``gsmsdr-eval``: ``ns-eval`` with optional test-pose alignment (:mod:`gsmsdr_ns.plugin.pose_alignment`).

Writes ns-eval's JSON (``experiment_name``, ``method_name``, ``checkpoint``, ``results`` with the given test poses)
plus, with ``--align-poses`` (the default), ``results_aligned`` (the same metrics after each test camera's pose was
optimised on the frozen scene) and ``views`` (per test view: both metrics and the pose correction found).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from gsmsdr_ns.io.atomic import write_json_atomic
from gsmsdr_ns.plugin.pose_alignment import PoseAlignmentConfig, evaluate_with_alignment


@dataclass
class EvalWithAlignment:
    """Evaluate a trained run on its test views, with and without test-pose alignment."""

    load_config: Path
    """The run's config.yml (as for ns-eval)."""
    output_path: Path = Path("eval.json")
    """Where the metrics JSON is written (atomically)."""
    align_poses: bool = True
    """Also optimise each test camera's pose on the frozen scene and report the metrics after alignment."""
    alignment: PoseAlignmentConfig = field(default_factory=PoseAlignmentConfig)
    """How the poses are optimised."""

    def main(self) -> dict:
        from nerfstudio.utils.eval_utils import eval_setup

        import gsmsdr_ns.plugin  # noqa: F401  (checkpoint loading under torch's weights_only default)

        if not self.load_config.is_file():
            raise FileNotFoundError(f"gsmsdr-eval: config '{self.load_config}' does not exist; pass a run's "
                                    "config.yml (outputs/<scene>/<method>/<timestamp>/config.yml).")  # fmt: skip
        config, pipeline, checkpoint_path, _ = eval_setup(self.load_config)
        columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, transient=True) as progress:
            mean, mean_aligned, views = evaluate_with_alignment(
                pipeline, self.alignment, align=self.align_poses, progress=progress
            )
        payload = {
            "experiment_name": config.experiment_name,
            "method_name": config.method_name,
            "checkpoint": str(checkpoint_path),
            "results": mean,
        }
        if self.align_poses:
            payload["results_aligned"] = mean_aligned
        payload["views"] = views
        write_json_atomic(self.output_path, payload, indent=2)
        summary = ", ".join(f"{k}={v:.4f}" for k, v in mean.items())
        print(f"gsmsdr-eval: given poses: {summary}")
        if self.align_poses:
            print("gsmsdr-eval: aligned poses: " + ", ".join(f"{k}={v:.4f}" for k, v in mean_aligned.items()))
        print(f"gsmsdr-eval: wrote {self.output_path}")
        return payload


def entrypoint() -> None:
    """Console-script entry point: one-line errors, Ctrl-C exits 130 (the JSON is written only at the end)."""
    from rich.console import Console

    from gsmsdr_ns._cli import run_entrypoint

    run_entrypoint(lambda: tyro.cli(EvalWithAlignment), Console(stderr=True))


if __name__ == "__main__":
    entrypoint()
