"""HTML pieces of the run report: sections, tables, embedded figures and the page."""

from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass, field


@dataclass
class Section:
    """One part of the page: a title, HTML body and the figures (name -> PNG bytes) it embeds."""

    title: str
    body: str = ""
    figures: dict[str, bytes] = field(default_factory=dict)


def esc(x) -> str:
    return html.escape(str(x))


def fmt(x, digits: int = 3) -> str:
    if isinstance(x, float):
        return "–" if not math.isfinite(x) else f"{x:,.{digits}f}"
    if isinstance(x, int):
        return f"{x:,}"
    return esc(x) if x is not None else "–"


def table(header: list[str], rows: list[list]) -> str:
    """An HTML table; cells are escaped, numbers formatted (:func:`fmt`)."""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def img(name: str, data: bytes, caption: str = "") -> str:
    """A PNG embedded as a data URI in a <figure> whose id is ``name``."""
    b64 = base64.b64encode(data).decode()
    cap = f"<figcaption>{esc(caption or name)}</figcaption>"
    return f'<figure id="{esc(name)}"><img alt="{esc(name)}" src="data:image/png;base64,{b64}">{cap}</figure>'


# ------------------------------------------------------------------------------ page

_CSS = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:72em;color:#222}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}h3{font-size:1.05em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}td,th{border:1px solid #ddd;padding:.25em .6em;
text-align:right}th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
figure{display:inline-block;margin:.5em}img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.8em;color:#666}code{background:#f4f4f4;padding:0 .3em}.note{color:#a33}"""


def render_page(title: str, subtitle: str, sections: list[Section]) -> str:
    """The HTML page of ``sections`` (figures embedded as data URIs)."""
    parts = [(f"<!doctype html><html><head><meta charset='utf-8'><title>{esc(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{esc(title)}</h1><p>{esc(subtitle)}</p><nav><ol>")]
    parts += [f'<li><a href="#s{n}">{esc(s.title)}</a></li>' for n, s in enumerate(sections)]
    parts.append("</ol></nav>")
    for n, s in enumerate(sections):
        parts.append(f'<h2 id="s{n}">{esc(s.title)}</h2>{s.body}')
        parts += [img(name, data) for name, data in s.figures.items()]
    parts.append("</body></html>")
    return "\n".join(parts)
