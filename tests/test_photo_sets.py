"""Where photo sets are looked up: $GSMSDR_DATA_DIR first, then shared/data in the anchors' parent folders."""

from __future__ import annotations

from pathlib import Path

import pytest

from gsmsdr_ns.io.photo_sets import DATA_DIR_ENV, find_photo_set, photo_set_roots


def test_env_folder_first_then_shared_data_above_anchor(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    env_root, project = tmp_path / "sets", tmp_path / "project"
    anchor = project / "repo" / "configs"
    anchor.mkdir(parents=True)
    (project / "shared" / "data" / "fern" / "images_16").mkdir(parents=True)
    monkeypatch.setenv(DATA_DIR_ENV, str(env_root))
    roots = photo_set_roots([anchor])
    assert roots[0] == env_root and project / "shared" / "data" in roots
    assert find_photo_set("fern", [anchor], subfolder="images_16") == project / "shared" / "data" / "fern"
    # the same set under $GSMSDR_DATA_DIR wins
    (env_root / "fern" / "images_16").mkdir(parents=True)
    assert find_photo_set("fern", [anchor], subfolder="images_16") == env_root / "fern"
    # a set without the wanted sub-folder is not the set
    assert find_photo_set("fern", [anchor], subfolder="images_8") is None
    assert find_photo_set("no-such-set", [anchor]) is None
