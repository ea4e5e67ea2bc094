"""What a catalogue case puts in its folder before the command runs: small, declarative file makers."""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np
import yaml

from micro import Library, micro_config

__all__ = ["DROP", "Config", "Text", "Bytes", "Copy", "H5", "Truncated", "Folder", "Symlink", "Fifo", "Simulated",
           "Checkpoint", "SweepFolder", "make", "set_data", "drop", "set_attr"]

#: An override value that removes the key.
DROP = object()


def _apply(data: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = data
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    if value is DROP:
        node.pop(parts[-1], None)
    else:
        node[parts[-1]] = value


@dataclass(frozen=True)
class Config:
    """The micro config with dotted-key overrides (``{"noise.seed": True}``; :data:`DROP` removes a key)."""

    overrides: dict = field(default_factory=dict)

    def make(self, path: Path, lib: Library) -> None:
        data = micro_config()
        for key, value in self.overrides.items():
            _apply(data, key, value)
        path.write_text(yaml.safe_dump(data, sort_keys=False))


@dataclass(frozen=True)
class Text:
    text: str

    def make(self, path: Path, lib: Library) -> None:
        path.write_text(self.text)


@dataclass(frozen=True)
class Bytes:
    data: bytes

    def make(self, path: Path, lib: Library) -> None:
        path.write_bytes(self.data)


@dataclass(frozen=True)
class Copy:
    """A copy of a library file or folder (``captures``, ``recon``, ``report``, ``run_dir`` …), then ``edit``."""

    source: str
    edit: Callable[[Path], None] | None = None

    def make(self, path: Path, lib: Library) -> None:
        source = getattr(lib, self.source)
        if source.is_dir():
            shutil.copytree(source, path)
        else:
            shutil.copy(source, path)
        if self.edit is not None:
            self.edit(path)


@dataclass(frozen=True)
class H5:
    """A new HDF5 file filled by ``build(handle)``."""

    build: Callable[[h5py.File], None] = lambda handle: None

    def make(self, path: Path, lib: Library) -> None:
        with h5py.File(path, "w") as handle:
            self.build(handle)


@dataclass(frozen=True)
class Truncated:
    """The first ``fraction`` of a library file's bytes."""

    source: str
    fraction: float = 0.5

    def make(self, path: Path, lib: Library) -> None:
        data = getattr(lib, self.source).read_bytes()
        path.write_bytes(data[: int(len(data) * self.fraction)])


@dataclass(frozen=True)
class Folder:
    children: dict = field(default_factory=dict)

    def make(self, path: Path, lib: Library) -> None:
        path.mkdir()
        for name, maker in self.children.items():
            maker.make(path / name, lib)


@dataclass(frozen=True)
class Symlink:
    target: str

    def make(self, path: Path, lib: Library) -> None:
        path.symlink_to(self.target)


@dataclass(frozen=True)
class Fifo:
    def make(self, path: Path, lib: Library) -> None:
        os.mkfifo(path)


@dataclass(frozen=True)
class Simulated:
    """captures.h5 of the micro config with dotted-key ``overrides`` (``{"simulate.store": "sensor"}``)."""

    overrides: dict = field(default_factory=dict)

    def make(self, path: Path, lib: Library) -> None:
        from cca_cli.config.load import parse_config
        from cca_cli.stages import simulate
        from cca_cli.stages.runner import pick_sections, stage_provenance

        data = micro_config()
        for key, value in self.overrides.items():
            _apply(data, key, value)
        config = parse_config(data)
        simulate.run(config, path, provenance=stage_provenance("simulate", pick_sections(config, simulate.SECTIONS)))


class _Stop(Exception):
    pass


@dataclass(frozen=True)
class Checkpoint:
    """The checkpoint that ``cca reconstruct <captures> -o <this name without .checkpoint> --iterations N``
    resumes from (a real one, written at iteration 1 of an interrupted run), then ``edit``."""

    captures: str
    iterations: int
    edit: Callable[[Path], None] | None = None

    def make(self, path: Path, lib: Library) -> None:
        from cca_cli.config.model import ReconstructSection
        from cca_cli.stages import reconstruct
        from cca_cli.stages.runner import stage_provenance

        captures = path.parent / self.captures
        section = ReconstructSection(iterations=self.iterations, checkpoint_every=1)
        provenance = stage_provenance("reconstruct", {"reconstruct": section}, [captures])

        def stop_once_saved(event) -> None:
            if path.exists():
                raise _Stop

        try:
            reconstruct.run(captures, section, path.with_name(path.name.removesuffix(".checkpoint")),
                            provenance=provenance, progress=stop_once_saved)
        except _Stop:
            pass
        assert path.is_file(), "no checkpoint was written"
        if self.edit is not None:
            self.edit(path)


@dataclass(frozen=True)
class SweepFolder:
    """The folder of an earlier ``cca sweep <study>`` of the micro config (with ``overrides``) over ``sets``:
    its table, and each point complete (the library's run folder with the point's point.json)."""

    sets: dict
    overrides: dict = field(default_factory=dict)
    study: str = "grid"

    def make(self, path: Path, lib: Library) -> None:
        import json

        from cca_cli.config.load import parse_config
        from cca_cli.config.model import SweepSection
        from cca_cli.stages import sweep

        data = micro_config()
        for key, value in self.overrides.items():
            _apply(data, key, value)
        base = parse_config(data)
        spec = SweepSection(study=self.study, parameters=self.sets)
        points = sweep.expand_points(base, spec, path)
        for point in points:
            shutil.copytree(lib.run_dir, point.out_dir)
            result = {"status": "ok", "error": "", "wall_s": 1.0, "stages": {}}
            record = {"config_digest": sweep.config_digest(point.config), "index": point.index,
                      "overrides": point.overrides, "result": result}
            (point.out_dir / "point.json").write_text(json.dumps(record, indent=2))
        sweep.write_table(sweep.earlier_rows(points), path, spec=spec, base=base)


def make(files: dict, root: Path, lib: Library) -> None:
    """Create every ``name: maker`` of a case under ``root`` (names may contain ``/``)."""
    for name, maker in files.items():
        target = root / name
        target.parent.mkdir(parents=True, exist_ok=True)
        maker.make(target, lib)


# HDF5 edits (for Copy(..., edit=...)) ---------------------------------------------------------------------------

def _h5_edit(fn):
    def edit(path: Path) -> None:
        with h5py.File(path, "r+") as handle:
            fn(handle)
    return edit


def set_data(name: str, transform: Callable[[np.ndarray], np.ndarray]):
    """Replace dataset ``name`` by ``transform(old)`` (attributes kept)."""
    def fn(handle):
        old = handle[name]
        attrs = dict(old.attrs)
        data = transform(old[()])
        del handle[name]
        new = handle.create_dataset(name, data=data)
        new.attrs.update(attrs)
    return _h5_edit(fn)


def drop(*names: str):
    """Delete datasets, groups or (``"@attr"`` or ``"/group@attr"``) attributes."""
    def fn(handle):
        for name in names:
            if "@" in name:
                where, attr = name.split("@")
                del handle[where or "/"].attrs[attr]
            else:
                del handle[name]
    return _h5_edit(fn)


def set_attr(where: str, key: str, value):
    def fn(handle):
        handle[where].attrs[key] = value
    return _h5_edit(fn)
