"""A config's own mistakes, said at load time with the config file and key."""

from __future__ import annotations

import pytest

from cca_cli.config.load import load_config
from cca_cli.errors import InputError


def test_a_manifest_the_config_names_that_is_not_there_names_the_key_and_where_it_was_looked_for(tmp_path):
    (tmp_path / "configs").mkdir()
    config = tmp_path / "configs" / "lab.yaml"
    config.write_text("run: {stages: [ingest, reconstruct, report]}\ningest: {manifest: ../lab/manifest.yaml}\n")
    with pytest.raises(InputError, match=r"lab.yaml: ingest.manifest: ../lab/manifest.yaml not found \(.*/lab/"
                                          r"manifest.yaml\); a relative path is read from the config's folder"):
        load_config(config)
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "manifest.yaml").write_text("images: []\n")
    assert load_config(config).ingest.manifest == tmp_path / "configs" / ".." / "lab" / "manifest.yaml"
    # a config whose stages do not ingest does not need the manifest
    config.write_text("run: {stages: [reconstruct, report]}\ningest: {manifest: elsewhere.yaml}\n")
    assert load_config(config).ingest is not None
