"""The pieces every ``report.html`` is built of: the page shell and its style sheet, sections,
tables, legends, figures embedded as ``data:`` URIs, option tables.

Every page opens from disk with no network and no JavaScript: every figure is a PNG embedded
as a ``data:`` URI, the style sheet is inline, and the only links are to the page's own
sections.
"""

from __future__ import annotations

import base64
import html
import math
import re
from collections.abc import Mapping, Sequence

from ._format import format_number

__all__ = [
    "escape",
    "figure_html",
    "table_html",
    "key_value_table",
    "legend_list",
    "page_html",
    "SELF_CONTAINED",
    "slug_ids",
    "interval_text",
    "value_ci",
    "flat_items",
    "item_text",
    "options_table",
]


# The tables must fit a 1280 px window (with its scroll bar) in wide fonts such as DejaVu
# Sans, or the Flags column ends up behind a sideways scroll (tests/test_report_browser.py
# measures this in Chromium). Hence: a page 1240 px wide at most, 5 px cell padding, and
# names (a row's first cell) and file paths (code) that break anywhere, since names such as
# "groupwise_bspline_grid8mm" have no space to break at; numbers never break.
_CSS = """
body{font-family:-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;margin:0;color:#222;
background:#fafafa;line-height:1.45;overflow-wrap:break-word}
main{max-width:1240px;margin:0 auto;padding:0 24px 48px}
header{background:#2c3e50;color:#fff;padding:18px 24px}
header h1{margin:0;font-size:1.6em}header p{margin:4px 0 0;color:#d5dde5}
h2{border-bottom:2px solid #2c3e50;padding-bottom:4px;margin-top:36px}
h3{margin-bottom:4px}
nav ol{columns:2;margin:0}a{color:#1f5f99}nav a,a.top{color:#1f5f99;text-decoration:none}
nav a:hover{text-decoration:underline}
a.top{font-size:.85em;float:right;font-weight:normal}
.verdict{background:#eaf4ea;border-left:6px solid #2e7d32;padding:10px 16px;font-size:1.1em}
.verdict.flagged{background:#fdf0e6;border-left-color:#d9822b}
table{border-collapse:collapse;margin:8px 0 12px;font-size:.9em;background:#fff}
th,td{border:1px solid #ccd;padding:3px 5px;text-align:right;vertical-align:top}
th{background:#e8edf2}td:first-child,th:first-child{text-align:left}
td{white-space:nowrap}td.text{text-align:left;max-width:420px;white-space:normal}
td.text:first-child,td.text code{overflow-wrap:anywhere}
tr.flagged td{background:#fff4ec}tr.best td{background:#eaf4ea}
dl.legend{font-size:.88em;background:#fff;border:1px solid #dde;padding:8px 14px;
columns:2;column-gap:28px}
dl.legend dt,dl.legend dd{break-inside:avoid}dl.legend dt{break-after:avoid}
dl.legend dt{font-weight:bold;margin-top:6px}dl.legend dd{margin-left:18px}
figure{margin:12px 12px 12px 0;background:#fff;border:1px solid #dde;padding:8px;
display:inline-table;vertical-align:top}
figure img{max-width:100%;height:auto;display:block}
figure.half img{max-width:560px}
figcaption{font-size:.86em;color:#444;display:table-caption;caption-side:bottom;
background:#fff;border:1px solid #dde;border-top:0;padding:4px 8px 8px}
.flag{color:#b34700;font-weight:bold}a.flag{white-space:nowrap}
.ci{color:#555;font-size:.85em;white-space:nowrap}
div.wide{overflow-x:auto}
code{background:#eef;padding:0 3px}
details{margin:6px 0}
footer{font-size:.8em;color:#666;margin-top:40px}
"""


def escape(text) -> str:
    """`text` (any value, as ``str``) safe inside HTML and in attribute values."""
    return html.escape(str(text), quote=True)


def _img(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{escape(alt)}">'


def figure_html(png: bytes, alt: str, caption: str, *, css: str = "") -> str:
    """A ``<figure>``: the PNG embedded as a ``data:`` URI, `alt` (plain text), `caption`
    (HTML), and an optional CSS class (``"half"``: two side by side)."""
    cls = f' class="{css}"' if css else ""
    return f"<figure{cls}>{_img(png, alt)}<figcaption>{caption}</figcaption></figure>"


def table_html(
    head: Sequence[str],
    rows: Sequence[Sequence[str]],
    *,
    text: Sequence[int] = (0,),
    classes: Sequence[str] | None = None,
    ids: Sequence[str] | None = None,
    wide: bool = False,
) -> str:
    """An HTML table of cells already in HTML.

    Parameters
    ----------
    head : sequence of str
        Column headings (HTML); empty for a table of rows headed by their first cell.
    rows : sequence of sequence of str
        The cells (HTML), one sequence per row.
    text : sequence of int
        Columns of words, left-aligned and wrapped (negative counts from the end); the
        others are numbers, right-aligned.
    classes, ids : sequence of str, optional
        Per row, a CSS class (e.g. ``"flagged"``) and an id (a link target); "" for none.
    wide : bool
        Scroll sideways rather than overflow the page (many columns).
    """
    out = []
    if head:
        out.append("<thead><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead>")
    out.append("<tbody>")
    for k, cells in enumerate(rows):
        words = {i % len(cells) for i in text}
        cls = classes[k] if classes else ""
        rid = ids[k] if ids else ""
        attrs = (f' class="{cls}"' if cls else "") + (f' id="{rid}"' if rid else "")
        tds = "".join(
            f'<td class="text">{c}</td>' if i in words else f"<td>{c}</td>"
            for i, c in enumerate(cells)
        )
        out.append(f"<tr{attrs}>{tds}</tr>")
    out.append("</tbody>")
    table = "<table>" + "".join(out) + "</table>"
    return f'<div class="wide">{table}</div>' if wide else table


def key_value_table(rows: Sequence[tuple[str, str]]) -> str:
    """A two-column table of (name, HTML value), names as row headings."""
    body = "".join(f'<tr><th>{escape(k)}</th><td class="text">{v}</td></tr>' for k, v in rows)
    return f"<table><tbody>{body}</tbody></table>"


def legend_list(items: Sequence[tuple[str, str]]) -> str:
    """A legend of terms: (term, HTML definition) pairs, in two columns."""
    body = "".join(f"<dt>{escape(k)}</dt><dd>{v}</dd>" for k, v in items)
    return f'<dl class="legend">{body}</dl>'


def _section(sid: str, title: str, *parts: str) -> str:
    """A section the contents link to, headed by `title` and a link back to the contents."""
    return (
        f'<section id="{sid}"><h2>{escape(title)} <a class="top" href="#contents">contents '
        "&uarr;</a></h2>\n" + "\n".join(p for p in parts if p) + "\n</section>"
    )


def page_html(
    *,
    title: str,
    heading: str,
    subtitle: str,
    sections: Sequence[tuple[str, str, str]],
    footer: str,
) -> str:
    """The whole page: header, contents, the sections in order, footer.

    Parameters
    ----------
    title : str
        The browser tab's title (plain text).
    heading, subtitle : str
        The banner's title (plain text) and the line under it (HTML).
    sections : sequence of (str, str, str)
        ``(id, heading, body HTML)``; the contents list them in this order.
    footer : str
        HTML.
    """
    nav = "".join(f'<li><a href="#{sid}">{escape(t)}</a></li>' for sid, t, _ in sections)
    body = [
        f"<header><h1>{escape(heading)}</h1><p>{subtitle}</p></header>",
        "<main>",
        f'<nav id="contents"><h2>Contents</h2><ol>{nav}</ol></nav>',
        *[_section(sid, t, html_) for sid, t, html_ in sections],
        f"<footer>{footer}</footer>",
        "</main>",
    ]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{escape(title)}</title>"
        f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n"
    )


SELF_CONTAINED = (
    "Written by itk-nrreval: one self-contained file (figures embedded, no script, no network)."
)


def slug_ids(names: Sequence[str], prefix: str = "reg-") -> dict[str, str]:
    """An id per name: `prefix` and the name's letters, digits, ``-`` and ``_``."""
    out: dict[str, str] = {}
    used: set[str] = set()
    for name in names:
        base = prefix + (re.sub(r"[^A-Za-z0-9_-]+", "-", name).strip("-") or "x")
        slug, k = base, 2
        while slug in used:
            slug, k = f"{base}-{k}", k + 1
        used.add(slug)
        out[name] = slug
    return out


def interval_text(iv) -> str:
    """A subject-level interval as ``[lo, hi]``; a dash when there is none or it is not finite."""
    if iv is None or not math.isfinite(iv.lo) or not math.isfinite(iv.hi):
        return "–"
    return f"[{format_number(iv.lo)}, {format_number(iv.hi)}]"


def value_ci(value: float, iv) -> str:
    """A score over its subject-level 95% interval (small, below)."""
    return f'{format_number(value)}<br><span class="ci">{interval_text(iv)}</span>'


def flat_items(d: Mapping, prefix: str = "") -> list[tuple[str, object]]:
    """Nested mappings as ``(dotted.name, value)`` pairs."""
    out = []
    for k, v in d.items():
        if isinstance(v, Mapping):
            out += flat_items(v, f"{prefix}{k}.")
        else:
            out.append((f"{prefix}{k}", v))
    return out


def item_text(value) -> str:
    """A value of the inputs or options for a reader: a dash when not set (None)."""
    return "–" if value is None else escape(value)


def options_table(options: Mapping) -> str:
    """Every option, nested ones dotted, values as code (a dash when not set)."""
    return key_value_table(
        [(k, "–" if v is None else f"<code>{escape(v)}</code>") for k, v in flat_items(options)]
    )
