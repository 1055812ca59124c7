"""The HTML page of ``torm report`` from its blocks, through a Jinja2 template (autoescaped).

Blocks are ``("h1" | "h2" | "h3" | "p", text)``, ``("table", headers, rows)`` and ``("img", file, caption)``;
text may hold Markdown's ``**bold**``, ``*italic*``, ```code``` and ``[link](href)`` spans, rendered as ``<b>``,
``<i>``, ``<code>`` and ``<a>``. Table cells do not wrap, so an interval such as ``12/20 (60% [39-78])`` stays on
one line; a table wider than the page scrolls sideways instead of being cut.
"""

from __future__ import annotations

import re
from typing import Any

import jinja2
from markupsafe import Markup, escape

TEMPLATE = """<!doctype html>
<html><head><meta charset="utf-8"><title>{{ title }}</title>
<style>
body { font-family: sans-serif; max-width: 1100px; margin: 2em auto; }
.scroll { overflow-x: auto; max-width: 100%; }
table { border-collapse: collapse; margin: 1em 0; }
td, th { border: 1px solid #bbb; padding: 3px 8px; text-align: left; white-space: nowrap; }
th { background: #eee; }
img { max-width: 100%; }
</style></head>
<body>
{% for b in blocks %}
{%- if b[0] in ("h1", "h2", "h3") %}<{{ b[0] }}>{{ b[1] | inline }}</{{ b[0] }}>
{%- elif b[0] == "p" %}<p>{{ b[1] | inline }}</p>
{%- elif b[0] == "table" %}<div class="scroll"><table>
<tr>{% for h in b[1] %}<th>{{ h | inline }}</th>{% endfor %}</tr>
{% for row in b[2] %}<tr>{% for c in row %}<td>{{ c | string | inline }}</td>{% endfor %}</tr>
{% endfor %}</table></div>
{%- elif b[0] == "img" %}<figure><img src="{{ b[1] }}" alt="{{ b[2] }}">
<figcaption>{{ b[2] | inline }}</figcaption></figure>
{%- endif %}
{% endfor %}
</body></html>
"""


def inline(text: Any) -> Markup:
    """Escape ``text`` and turn Markdown's ``**bold**``, ``*italic*``, ```code``` and ``[text](href)`` spans into
    ``<b>``, ``<i>``, ``<code>`` and ``<a>``."""
    t = str(escape(str(text)))
    t = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", t)
    t = re.sub(r"(?<![\w*])\*(?!\s)(.+?)(?<!\s)\*(?![\w*])", r"<i>\1</i>", t)
    t = re.sub(r"\[([^\]]+)\]\(([^)\s]+)\)", r'<a href="\2">\1</a>', t)
    return Markup(re.sub(r"`(.+?)`", r"<code>\1</code>", t))


_ENV = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True)
_ENV.filters["inline"] = inline
_PAGE = _ENV.from_string(TEMPLATE)


def to_html(blocks: list[tuple], title: str) -> str:
    """The report page for ``blocks`` (module docstring) titled ``title``."""
    return _PAGE.render(blocks=blocks, title=title)


__all__ = ["TEMPLATE", "inline", "to_html"]
