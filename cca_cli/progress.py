"""How stages and the libraries they drive report progress without knowing about terminals."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

__all__ = ["ProgressEvent", "ProgressFn", "silent"]


@dataclass(frozen=True)
class ProgressEvent:
    """A stage's progress: ``done`` of ``total`` steps of ``task``, with extra numbers in ``info``.

    A ``transient`` task (one of many running side by side, such as a tile) is shown
    while it runs and dropped once ``done`` reaches ``total``.
    """

    stage: str
    task: str
    done: int
    total: int
    info: dict[str, Any] = field(default_factory=dict)
    transient: bool = False


ProgressFn = Callable[[ProgressEvent], None]


def silent(event: ProgressEvent) -> None:
    """A progress callback that ignores everything."""
