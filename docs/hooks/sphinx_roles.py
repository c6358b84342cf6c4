"""MkDocs hook: the Sphinx roles in warpdem's docstrings (``:class:`Scene```, ``:meth:`~warpdem.x.Y.z```) shown as
plain code, as Sphinx would show them, instead of a literal ``:class:`` before the code span.

mkdocstrings renders a docstring's ``:class:`X``` as ``:class:<code>X</code>``; this drops the role and, for a
``~``-prefixed target, keeps only its last component.
"""

from __future__ import annotations

import re
from typing import Any

_ROLE = re.compile(r":(?:attr|class|data|exc|func|meth|mod|obj):<code>(~?)([^<]*)</code>")


def _plain(match: re.Match[str]) -> str:
    target = match.group(2)
    return f"<code>{target.rsplit('.', 1)[-1] if match.group(1) else target}</code>"


def on_page_content(html: str, **kwargs: Any) -> str:
    return _ROLE.sub(_plain, html)
