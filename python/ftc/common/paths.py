"""Where the package and its build products are: ``PACKAGE_DIR`` (this
package), ``REPO_ROOT`` (a checkout's root; meaningless when installed) and
``BUILD_DIR`` (``FTC_BUILD_DIR``, else ``<repo>/build``)."""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1]
REPO_ROOT = PACKAGE_DIR.parents[1]
BUILD_DIR = Path(os.environ.get("FTC_BUILD_DIR", REPO_ROOT / "build")).resolve()
