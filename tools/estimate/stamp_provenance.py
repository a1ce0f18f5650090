"""Record the provenance of ensembles fitted before it was recorded, their trees unchanged. Run from the repository
root::

    python -m tools.estimate.stamp_provenance --files K.json D.json --fitting-sets A B ... --scikit-learn 1.9.1

The block (:func:`~gsmsdr_ns.estimate.ensemble.make_provenance`) records ``--config``'s evidence settings: give
the ones the files were fitted with (the defaults, for the shipped files).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

import tyro

from gsmsdr_ns.estimate.config import EstimateConfig
from gsmsdr_ns.estimate.ensemble import make_provenance
from tools.estimate.fit_ensembles import stamp_provenance


@dataclass
class StampProvenanceCLI:
    """Write the provenance block into fitted ensemble files (:func:`~.fit_ensembles.stamp_provenance`)."""

    files: Tuple[Path, ...]
    """The ensemble JSON files to stamp."""
    fitting_sets: Tuple[str, ...]
    """Names of the sets they were fitted on (the --work folders' names)."""
    scikit_learn: str
    """The scikit-learn version they were fitted with ("unknown" when it was not recorded)."""
    config: EstimateConfig = dataclasses.field(default_factory=EstimateConfig)
    """The estimate settings their evidence was measured with."""

    def main(self) -> List[str]:
        provenance = make_provenance(self.config, self.fitting_sets, self.scikit_learn)
        for file in self.files:
            stamp_provenance(file, provenance)
            print(f"stamped {file}")
        return [str(f) for f in self.files]


if __name__ == "__main__":
    tyro.cli(StampProvenanceCLI).main()
