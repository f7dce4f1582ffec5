"""Where the test suite finds the shared real scenes, and the marker of the tests that read them.

The scenes live in ``shared/scenes`` beside the repository clone (``../shared/scenes``); the
environment variable ``GDPT_SHARED_SCENES`` points elsewhere. Tests that read them carry
``@pytest.mark.shared_scenes``. ``tests/conftest.py`` skips them, with the path in the reason,
when the folder is missing; in CI (``CI`` set to ``true`` or ``1``) a missing folder fails the
run instead, naming the path it looked at. Its terminal summary counts how many of them ran.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The shared real scenes: ``<name>/scene.xml`` folders.
SHARED_SCENES = Path(
    os.environ.get("GDPT_SHARED_SCENES")
    or Path(__file__).resolve().parents[3] / "shared" / "scenes"
)

#: Marker of the tests that read :data:`SHARED_SCENES`.
MARKER = "shared_scenes"


def in_ci() -> bool:
    """Whether the suite runs in CI (``CI=true``, as set by GitHub Actions, GitLab and others)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")
