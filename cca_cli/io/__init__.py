"""File formats: the HDF5 schema, atomic writes with provenance, image files."""
