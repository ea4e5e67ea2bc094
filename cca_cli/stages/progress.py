"""The stages' progress events (defined in :mod:`cca_cli.progress`, shared with the libraries the stages drive)."""

from cca_cli.progress import ProgressEvent, ProgressFn, silent

__all__ = ["ProgressEvent", "ProgressFn", "silent"]
