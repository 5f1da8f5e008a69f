"""Sphinx configuration: Markdown pages (MyST), the reference pages generated from the code at
every build (docs_build/reference.py) and the Python API from the docstrings (autodoc)."""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "docs_build"))

import figures  # noqa: E402 (the generators, beside the docs, not part of the package)
import reference  # noqa: E402

project = "indentation-rig"
author = "the indentation-rig authors"
extensions = ["myst_parser", "sphinx.ext.autodoc"]
# the API page: signatures as written, type hints in them, members in the source's order
autodoc_typehints = "signature"
autodoc_member_order = "bysource"
autodoc_default_options = {"members": False}
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
html_theme = "furo"
html_title = "indentation-rig"
# console and output blocks wrap at the text column (docs/_static/console.css)
html_static_path = ["_static"]
html_css_files = ["console.css"]
myst_heading_anchors = 4
myst_enable_extensions = ["colon_fence"]
# no typographic dashes or quotes: a command's `--option` written in plain text (the reference pages
# take the parser's help as it is) must stay two hyphens, not become an en dash a technician copies
smartquotes = False
# `name` in a docstring is code, as it is in Markdown (not the title reference reST makes of it)
default_role = "literal"


def _write_reference(app) -> None:
    # written into the source tree before Sphinx reads it, as sphinx-apidoc does; never edited by
    # hand (git ignores them)
    for path, make in reference.PAGES.items():
        out = HERE / path
        out.parent.mkdir(parents=True, exist_ok=True)
        text = make()
        if not out.exists() or out.read_text() != text:
            out.write_text(text)


def _draw_figures(app) -> None:
    # drawn by the tool at every build into docs/_generated/ (git ignores it), as the reference
    # pages are written
    figures.make(HERE / "_generated", HERE.parent)


def setup(app) -> None:
    app.connect("builder-inited", _write_reference)
    app.connect("builder-inited", _draw_figures)

# an unreachable host should cost the link check seconds, not minutes
linkcheck_timeout = 10
linkcheck_retries = 1
