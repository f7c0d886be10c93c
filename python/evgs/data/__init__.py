"""Data on disk: the canonical sequence layout, trajectory files, and data-set adapters."""
