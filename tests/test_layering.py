"""Import rules between layers, checked on the source (ast), so they hold without running anything."""

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cca_cli"

#: The numeric core: no files, no config, no terminal, no plotting.
CORE = ["engines", "optics", "sampling", "targets", "metrics", "units.py", "library"]
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


#: Each package (or top-level module) and its layer: a module may import its own layer and those below, never above.
#: commands → stages → api → workflows → {io, config, report} → library → {engines, registration, hdr, metrics}
#: → {optics, sampling, targets} → {units, errors, progress, values, version}.
LAYERS = {
    "units.py": 0, "errors.py": 0, "progress.py": 0, "values.py": 0, "version.py": 0,
    "optics": 1, "sampling": 1, "targets": 1,
    "engines": 2, "registration": 2, "hdr": 2, "metrics": 2,
    "library": 3,
    "io": 4, "config": 4, "report": 4,
    "workflows": 5,
    "api.py": 6,
    "stages": 7,
    "commands": 8,
    "__main__.py": 9, "__init__.py": 9,
}

#: Stage modules that run other stages (orchestration): they may import any stage.
STAGE_ORCHESTRATORS = {
    "runner.py",   # runs the stages of a pipeline in order
    "sweep.py",    # runs whole pipelines per sweep point and reads their reports
}
#: Stage modules every stage may import: shared infrastructure, not a stage.
STAGE_INFRASTRUCTURE = {
    "progress",    # the progress events of every stage (re-exported from cca_cli.progress)
}


def _entry(path: Path) -> str:
    return path.relative_to(PACKAGE).parts[0]


def _layer_of_import(name: str) -> int | None:
    """The layer of an imported name: a module of the package, or a name the package's ``__init__`` holds."""
    parts = name.split(".")
    if parts[0] != "cca_cli":
        return None
    if len(parts) < 2:
        return LAYERS["__init__.py"]
    layer = LAYERS.get(parts[1], LAYERS.get(parts[1] + ".py"))
    return LAYERS["__init__.py"] if layer is None else layer


def _upward_imports(paths) -> list[str]:
    found = []
    for path in paths:
        own = LAYERS[_entry(path)]
        for name in sorted(_imports(path)):
            layer = _layer_of_import(name)
            if layer is not None and layer > own:
                found.append(f"{path.relative_to(PACKAGE.parent)} (layer {own}) imports {name} (layer {layer})")
    return found


def _stage_to_stage_imports(paths) -> list[str]:
    found = []
    for path in paths:
        if path.name in STAGE_ORCHESTRATORS:
            continue
        for name in sorted(_imports(path)):
            parts = name.split(".")
            if parts[:2] != ["cca_cli", "stages"] or len(parts) < 3:
                continue
            if parts[2] not in STAGE_INFRASTRUCTURE and parts[2] != path.stem:
                found.append(f"{path.relative_to(PACKAGE.parent)} imports {name}")
    return found


def test_every_package_has_a_layer():
    entries = {p.name for p in PACKAGE.iterdir() if (p.is_dir() and (p / "__init__.py").exists()) or p.suffix == ".py"}
    assert entries == set(LAYERS)


def test_no_module_imports_a_higher_layer():
    assert _upward_imports(sorted(PACKAGE.rglob("*.py"))) == []


def test_no_stage_imports_another_stage():
    stages = sorted((PACKAGE / "stages").glob("*.py"))
    assert _stage_to_stage_imports(stages) == []
    for name in STAGE_ORCHESTRATORS | {f"{n}.py" for n in STAGE_INFRASTRUCTURE}:
        assert (PACKAGE / "stages" / name).is_file(), name


def test_only_io_imports_h5py():
    paths = [p for p in PACKAGE.rglob("*.py") if _entry(p) != "io"]
    assert _violations(paths, ("h5py",)) == []


def test_the_layer_checks_catch_what_they_forbid(tmp_path, monkeypatch):
    package = tmp_path / "cca_cli"
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    (package / "stages").mkdir(parents=True)
    (package / "optics").mkdir()
    borrowing = package / "stages" / "simulate.py"
    borrowing.write_text("from .progress import silent\nfrom . import simulate\n\n"
                         "def f():\n    from cca_cli.stages import reconstruct\n    import h5py\n")
    clean = package / "stages" / "report.py"
    clean.write_text("from cca_cli.stages.progress import silent\nfrom cca_cli.io.h5 import open_input\n")
    orchestrator = package / "stages" / "runner.py"
    orchestrator.write_text("from cca_cli.stages import simulate as simulate_stage\n")
    upward = package / "optics" / "fft.py"
    upward.write_text("def f():\n    from ..workflows import scenes\n")
    from_top = package / "optics" / "pupil.py"
    from_top.write_text("from cca_cli import __version__\n")

    assert _stage_to_stage_imports([borrowing, clean, orchestrator]) == [
        "cca_cli/stages/simulate.py imports cca_cli.stages.reconstruct"]
    assert _violations([borrowing, clean], ("h5py",)) == ["cca_cli/stages/simulate.py imports h5py"]
    assert _upward_imports([borrowing, clean, orchestrator, upward, from_top]) == [
        f"cca_cli/optics/fft.py (layer 1) imports cca_cli.workflows (layer {LAYERS['workflows']})",
        f"cca_cli/optics/fft.py (layer 1) imports cca_cli.workflows.scenes (layer {LAYERS['workflows']})",
        f"cca_cli/optics/pupil.py (layer 1) imports cca_cli (layer {LAYERS['__init__.py']})",
        f"cca_cli/optics/pupil.py (layer 1) imports cca_cli.__version__ (layer {LAYERS['__init__.py']})"]


def test_the_checker_sees_relative_and_function_local_imports(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from ..io import h5\nfrom . import fft\n\ndef f():\n    import yaml\n")
    names = _imports(probe, package="cca_cli.optics")
    assert {"cca_cli.io", "cca_cli.io.h5", "cca_cli.optics.fft", "yaml"} <= names
    assert not any(_matches(n, "cca_cli.iox") for n in names)
