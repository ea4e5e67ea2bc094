"""What a stage records of how it was made: the config sections it read, their hash, its inputs' hashes.

Kept apart from :mod:`cca_cli.stages.runner` so that a one-stage command records its provenance without
importing every stage.
"""

from __future__ import annotations

import hashlib
import json

import yaml
from pydantic import BaseModel

from cca_cli.config.model import RunConfig
from cca_cli.io.h5 import Provenance

__all__ = ["pick_sections", "section_yaml", "config_hash", "stage_provenance"]


def pick_sections(config: RunConfig, names: tuple[str, ...]) -> dict[str, BaseModel]:
    """The named sections of ``config`` (optional sections that are absent are left out)."""
    return {name: getattr(config, name) for name in names if getattr(config, name) is not None}


def section_yaml(sections: dict[str, BaseModel]) -> str:
    """YAML of config sections, as stored in provenance."""
    return yaml.safe_dump({k: v.model_dump(mode="json") for k, v in sections.items()}, sort_keys=False)


def config_hash(sections: dict[str, BaseModel]) -> str:
    """SHA-256 of the JSON form of config sections (without the keys that say only where a run computes,
    a section's ``NOT_RECIPE``, such as ``reconstruct.device``)."""
    data = {k: v.model_dump(mode="json", exclude=set(getattr(v, "NOT_RECIPE", ()))) for k, v in sections.items()}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def stage_provenance(stage: str, sections: dict[str, BaseModel], inputs=()) -> Provenance:
    """Provenance of one stage run: the YAML and hash of the sections it reads, and its inputs' hashes."""
    return Provenance.make(stage, section_yaml(sections), config_hash(sections), list(inputs))
