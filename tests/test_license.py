"""The licence the package declares is the one it ships: pyproject.toml names Apache-2.0 (an SPDX expression) and a
licence file at the repository root, and that file is the Apache License 2.0 as the Apache Software Foundation
publishes it.

Oracle: the SHA-256 of https://www.apache.org/licenses/LICENSE-2.0.txt, so any edit of the text (a filled-in
appendix, a changed line ending) fails. Whether the wheel carries the file needs a built wheel, which needs the
network for the build backend, so .ci/run checks it on the non-editable install it makes anyway (the installed
distribution's files hold ``licenses/LICENSE``).
"""

from __future__ import annotations

import hashlib
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
APACHE_2_0_SHA256 = "cfc7749b96f63bd31c3c42b5c471bf756814053e847c10f3eb003417bc523d30"


def test_declared_licence_file_is_the_apache_2_0_text():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "Apache-2.0"
    assert project["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_bytes()
    assert hashlib.sha256(text).hexdigest() == APACHE_2_0_SHA256
