"""YAML → :class:`RunConfig`, with one-line errors that name the file and the key."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from cca_cli.config.messages import accepted_keys, error_message, shown_value
from cca_cli.config.model import RunConfig
from cca_cli.config.yaml_text import read_yaml_file
from cca_cli.errors import ConfigError, InputError, short

__all__ = ["load_config", "parse_config", "dump_config", "preset_path", "PRESETS", "apply_overrides"]

#: Built-in presets shipped with the package.
PRESETS = ("headline",)


def preset_path(name: str = "headline") -> Path:
    """Path of a built-in preset YAML."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return Path(str(resources.files("cca_cli.config") / "presets" / f"{name}.yaml"))


def _key_text(loc: tuple) -> str:
    """A dotted key for messages; parts the user wrote are cut short."""
    parts = [p if isinstance(p, str) and len(p) <= 40 else short(p, 40) for p in loc]
    return ".".join(str(p) for p in parts) or "(top level)"


def _describe(error: dict, source: str) -> str:
    key = _key_text(error["loc"])
    kind = error["type"]
    if kind == "extra_forbidden":
        accepted = sorted(accepted_keys(RunConfig, error["loc"]))
        return f"{source}: {key}: unknown key; accepted keys here: {', '.join(accepted)}"
    value = error.get("input")
    message = error_message(error)
    if kind.startswith(("float", "int", "bool", "finite")) or kind in (
            "greater_than", "less_than", "greater_than_equal", "less_than_equal", "literal_error"):
        return f"{source}: {key}: {message} (got {shown_value(value)})"
    return f"{source}: {key}: {message}"


def parse_config(data: Any, *, source: str = "config") -> RunConfig:
    """Validate a parsed YAML mapping.

    Raises
    ------
    ConfigError
        One line naming ``source``, the key and the accepted values.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: not a cca config: the top level must be a mapping of sections "
                          f"({', '.join(RunConfig.model_fields)}), got {type(data).__name__}")
    if data and not set(map(str, data)) & set(RunConfig.model_fields):
        raise ConfigError(f"{source}: not a cca config: none of its top-level keys is a section "
                          f"({', '.join(RunConfig.model_fields)})")
    try:
        return RunConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_describe(exc.errors()[0], source)) from None


def load_config(path: str | Path | None = None) -> RunConfig:
    """Read and validate a YAML config; ``None`` loads the built-in headline preset.

    Raises
    ------
    ConfigError
        One line naming ``path``: not a readable YAML text file, empty, not a config, or an invalid key.
    InputError
        The manifest ``ingest.manifest`` names is not there (when the config's stages ingest).
    """
    path = preset_path() if path is None else Path(path)
    data = read_yaml_file(path, what="config")
    if data is None or data == {}:
        raise ConfigError(f"{path}: the config is empty; write its sections (see configs/headline.yaml), "
                          "or give no CONFIG to run the built-in default")
    config = _resolve_relative_paths(parse_config(data, source=str(path)), path.parent)
    manifest = config.ingest.manifest if config.ingest is not None else None
    if manifest is not None and "ingest" in config.run.stages and not manifest.exists():
        given = data.get("ingest", {}).get("manifest") if isinstance(data.get("ingest"), dict) else None
        relative = f"; a relative path is read from the config's folder ({path.parent.resolve()})" \
            if given is not None and not Path(str(given)).is_absolute() else ""
        raise InputError(f"{path}: ingest.manifest: {given if given is not None else manifest} not found "
                          f"({manifest.resolve()}){relative}; check the path")
    return config


def _resolve_relative_paths(config: RunConfig, base: Path) -> RunConfig:
    """Paths that name input files (ingest.manifest, reconstruct.init) are relative to the config file's directory."""
    if config.ingest is not None and not config.ingest.manifest.is_absolute():
        ingest = config.ingest.model_copy(update={"manifest": base / config.ingest.manifest})
        config = config.model_copy(update={"ingest": ingest})
    init = config.reconstruct.init
    if init is not None and not init.is_absolute():
        config = config.model_copy(update={"reconstruct": config.reconstruct.model_copy(update={"init": base / init})})
    return config


def dump_config(config: BaseModel) -> str:
    """Resolved config (or section) as YAML text, for provenance and `--write-config`."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def apply_overrides(config: RunConfig, overrides: dict[str, Any], *, source: str = "--set") -> RunConfig:
    """A copy of ``config`` with dotted keys (``array.overlap``) replaced, re-validated."""
    data = config.model_dump(mode="json")
    for dotted, value in overrides.items():
        parts = dotted.split(".")
        node = data
        for part in parts[:-1]:
            if not isinstance(node.get(part), dict):
                raise ConfigError(f"{source}: {dotted}: no such section {part!r}")
            node = node[part]
        node[parts[-1]] = value
    return parse_config(data, source=source)
