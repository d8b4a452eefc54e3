"""ptovs: open-vocabulary 3D understanding of landmarks from photo collections."""

from __future__ import annotations

__version__ = "0.1.0"
