"""Merging exposure brackets into linear radiance (numeric core: arrays in, arrays out)."""

from cca_cli.hdr.merge import HdrResult, NoiseModel, estimate_noise, merge_exposures

__all__ = ["HdrResult", "NoiseModel", "estimate_noise", "merge_exposures"]
