"""The data's mode labels, without torch (``immnet data generate --single-mode`` lists them at ``--help``)."""

MODE_NAMES = ("cv", "ca", "ct+", "ct-")
"""Data mode labels, in the fixed order of docs/spec.md: 0 CV, 1 CA, 2 CT+, 3 CT-."""
N_MODES = len(MODE_NAMES)
MODE_LABELS = tuple(name.upper() for name in MODE_NAMES)
"""The data modes as tables and figures print them: CV, CA, CT+, CT-."""
