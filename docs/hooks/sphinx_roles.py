"""MkDocs hook: Sphinx cross-reference roles in docstrings render as code, not as literal ``:func:`` text.

torm's docstrings use Sphinx roles (``:func:`run_trial```, ``:class:`~torm.types.Capture```), which Sphinx, IDEs and
``help()`` readers understand; mkdocstrings' Google-style renderer shows the role's name as text before the code
span. This hook drops the role (and a leading ``~``'s module path, as Sphinx displays it) from every rendered page.
"""

from __future__ import annotations

import re

ROLE_HTML = re.compile(r":(?:py:)?(?:mod|func|class|data|meth|attr|exc|obj|const|ref|doc):<code>(~?)([^<]*)</code>")


def _strip(match: re.Match) -> str:
    tilde, target = match.group(1), match.group(2)
    return f"<code>{target.rsplit('.', 1)[-1] if tilde else target}</code>"


def on_page_content(html: str, **kwargs) -> str:
    """Rewrite ``:role:<code>target</code>`` as ``<code>target</code>`` (``~a.b.c`` -> ``c``)."""
    return ROLE_HTML.sub(_strip, html)
