"""The README's HDF5 schema table lists every dataset of cca_cli.io.schema."""

from pathlib import Path

from cca_cli.io.schema import DATASETS


def test_readme_lists_every_schema_dataset():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    missing = [d.path for d in DATASETS if f"| `{d.path}` |" not in readme]
    assert not missing, f"README schema table lacks {missing}; regenerate it from cca_cli/io/schema.py"
