"""Merge multi-exposure (HDR) brackets into linear radiance maps (numpy only)."""

from cca_cli.hdr.merge import HdrResult, merge_exposures

__all__ = ["HdrResult", "merge_exposures"]
