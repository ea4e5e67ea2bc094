"""Import rules between layers, checked on the source (ast), so they hold without running anything."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cca_cli"

#: The numeric core: no files, no config, no terminal, no plotting.
CORE = ["engines", "optics", "sampling", "targets", "metrics", "units.py"]
FORBIDDEN_IN_CORE = ("h5py", "yaml", "typer", "rich", "matplotlib", "cca_cli.io", "cca_cli.config",
                     "cca_cli.stages", "cca_cli.commands")


def _modules(entry: str) -> list[Path]:
    path = PACKAGE / entry
    return [path] if path.is_file() else sorted(path.rglob("*.py"))


def _imports(path: Path, package: str | None = None) -> set[str]:
    """Every module name imported anywhere in the file (also inside functions), made absolute."""
    tree = ast.parse(path.read_text(), filename=str(path))
    if package is None:
        package = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts[:-1])
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
    return names


def _matches(name: str, forbidden: str) -> bool:
    return name == forbidden or name.startswith(forbidden + ".")


def _violations(paths, forbidden):
    found = []
    for path in paths:
        for name in sorted(_imports(path)):
            if any(_matches(name, f) for f in forbidden):
                found.append(f"{path.relative_to(PACKAGE.parent)} imports {name}")
    return found


def test_the_core_lists_exist():
    for entry in CORE:
        assert _modules(entry), entry


@pytest.mark.parametrize("entry", CORE)
def test_numeric_core_imports_no_io_config_cli_or_plotting(entry):
    assert _violations(_modules(entry), FORBIDDEN_IN_CORE) == []


def test_only_the_figures_module_imports_matplotlib():
    paths = [p for p in PACKAGE.rglob("*.py") if p != PACKAGE / "report" / "figures.py"]
    assert _violations(paths, ("matplotlib",)) == []


def test_only_registration_imports_opencv():
    paths = [p for p in PACKAGE.rglob("*.py") if "registration" not in p.relative_to(PACKAGE).parts[:1]]
    assert _violations(paths, ("cv2",)) == []


def test_the_checker_sees_relative_and_function_local_imports(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from ..io import h5\nfrom . import fft\n\ndef f():\n    import yaml\n")
    names = _imports(probe, package="cca_cli.optics")
    assert {"cca_cli.io", "cca_cli.io.h5", "cca_cli.optics.fft", "yaml"} <= names
    assert not any(_matches(n, "cca_cli.iox") for n in names)
