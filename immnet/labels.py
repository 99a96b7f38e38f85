"""The data's mode labels, without torch (``immnet data generate --single-mode`` lists them at ``--help``)."""

MODE_NAMES = ("cv", "ca", "ct+", "ct-")
"""Data mode labels, in the fixed order of docs/spec.md: 0 CV, 1 CA, 2 CT+, 3 CT-."""
