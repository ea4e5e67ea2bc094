"""The library: arrays, geometry and options in, results out.

Below the files (:mod:`cca_cli.io`) and the configs (:mod:`cca_cli.config`):
nothing here reads a path or a config section. The Python interface
(:mod:`cca_cli.api`) and the command line's stages both call it, so a
recovery is the same whichever way it is asked for.
"""
