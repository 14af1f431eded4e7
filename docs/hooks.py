"""mkdocs hook: the CLI reference page, generated from the command line's own parsers (so it
cannot drift from them). A page holding ``<!-- cli-reference -->`` gets every command's
``--help``."""

from __future__ import annotations

import argparse
import os


def on_page_markdown(markdown, page, config, files):
    marker = "<!-- cli-reference -->"
    if marker not in markdown:
        return markdown
    os.environ["COLUMNS"] = "100"  # argparse's width
    from gyrojax.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    parts = ["```text", parser.format_help().rstrip(), "```", ""]
    for name, command in sub.choices.items():
        parts += [f"## gyrojax {name}", "", "```text", command.format_help().rstrip(), "```", ""]
    return markdown.replace(marker, "\n".join(parts))
