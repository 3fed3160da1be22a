"""Old import paths that still work for one release: each names its module's new home."""

from __future__ import annotations

import importlib
import sys
import warnings

__all__ = ["alias_module"]


def alias_module(old: str, new: str) -> None:
    """Make ``import old`` give module ``new`` itself, with one FutureWarning naming the new path.

    The old name is bound to the very same module object, so attributes read, set or patched
    through either name are the same.
    """
    warnings.warn(f"{old} moved to {new}; the old path goes in the next release", FutureWarning, stacklevel=3)
    sys.modules[old] = importlib.import_module(new)
