"""Files the catalogue's cases start from, built once per session from the micro config."""

from __future__ import annotations

import shutil

import pytest
import yaml
from micro import Library, micro_config, write_manifest


@pytest.fixture(scope="session")
def library(tmp_path_factory) -> Library:
    from typer.testing import CliRunner

    from cca_cli.commands.app import app

    root = tmp_path_factory.mktemp("library")
    config = root / "micro.yaml"
    config.write_text(yaml.safe_dump(micro_config(), sort_keys=False))
    runner = CliRunner()
    for args in (["simulate", str(config), "-o", str(root / "captures.h5"), "-q"],
                 ["reconstruct", str(root / "captures.h5"), "-o", str(root / "recon.h5"), "-c", str(config), "-q"],
                 ["report", str(root / "recon.h5"), "-o", str(root / "report")]):
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
    with_figures = micro_config()
    with_figures["report"]["figures"] = True
    figures_config = root / "figures.yaml"
    figures_config.write_text(yaml.safe_dump(with_figures, sort_keys=False))
    result = runner.invoke(app, ["run", str(figures_config), "--out-dir", str(root / "run"), "-q"])
    assert result.exit_code == 0, result.output
    try:
        write_manifest(root / "lab")
    except ImportError:  # OpenImageIO missing: the manifest cases that need images are skipped
        shutil.rmtree(root / "lab", ignore_errors=True)
    return Library(config=config, captures=root / "captures.h5", recon=root / "recon.h5", report=root / "report",
                   run_dir=root / "run", manifest_dir=root / "lab")
