"""MkDocs hook: the pages' lists render on the site as they do on GitHub.

The pages are written for GitHub's Markdown (CommonMark), where a list may follow a paragraph line directly and a
nested item is indented by its parent's marker width (2 spaces under ``- ``). MkDocs' Python-Markdown needs a
blank line before a list and 4 spaces per nesting level; without this hook such lists run into the paragraph
above them ("...: - **Holes.** ...") and nested items flatten. Before a page is rendered:

- a blank line goes before a list item that follows a paragraph line (as in CommonMark, an ordered item
  interrupts a paragraph only when it starts at 1);
- inside a list, indentation is doubled, so 2-space nesting and continuation become Python-Markdown's 4.

Fenced code blocks are left as they are. Registered in ``mkdocs.yml`` (``hooks:``).
"""

from __future__ import annotations

import re
from typing import Any

_ITEM = re.compile(r"^(?P<indent> *)(?:[-*+]|(?P<number>\d{1,9})[.)])(?: +\S| *$)")
_FENCE = re.compile(r"^ *(?P<fence>`{3,}|~{3,})")
#: lines that open a block of their own, after which a list needs no blank line
_BLOCK_START = ("#", "|", "<", ">")


def _interrupts_paragraph(item: re.Match[str]) -> bool:
    number = item.group("number")
    return number is None or int(number) == 1


def gfm_lists(markdown: str) -> str:
    """``markdown`` with GitHub-style lists rewritten for Python-Markdown (see the module docstring)."""
    out: list[str] = []
    fence: str | None = None
    in_list = False
    prev = ""
    for line in markdown.split("\n"):
        opening = _FENCE.match(line)
        if fence is not None:  # inside a fenced code block: unchanged
            if opening and opening.group("fence").startswith(fence[0]) and len(opening.group("fence")) >= len(fence):
                fence = None
            out.append(line)
            prev = line
            continue
        if opening:
            fence = opening.group("fence")
            if not line.startswith(" "):
                in_list = False  # an unindented fence ends a list, as on GitHub
            out.append(line)
            prev = line
            continue
        item = _ITEM.match(line)
        if item:
            after_paragraph = prev.strip() and not in_list and not prev.lstrip().startswith(_BLOCK_START)
            if after_paragraph and _interrupts_paragraph(item):
                out.append("")
            if after_paragraph and not _interrupts_paragraph(item):
                item = None  # a paragraph line that starts with a number, as CommonMark reads it
            else:
                in_list = True
        if line.strip() and in_list:
            if not item and not line.startswith(" ") and not prev.strip():
                in_list = False  # an unindented paragraph after a blank line ends the list
            elif line.lstrip().startswith("#"):
                in_list = False
            else:
                indent = len(line) - len(line.lstrip(" "))
                line = " " * (2 * indent) + line[indent:]
        out.append(line)
        prev = line
    return "\n".join(out)


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    return gfm_lists(markdown)
