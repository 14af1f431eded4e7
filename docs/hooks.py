"""mkdocs hooks.

- The CLI reference page, generated from the command line's own parsers (so it cannot drift
  from them): a page holding ``<!-- cli-reference -->`` gets every command's ``--help``.
- The notebooks rendered as pages (``notebooks/<name>.md``): their markdown cells as they are,
  their code cells as Python blocks. The notebooks are stored without outputs; the slow test
  suite executes every one of them and their own asserts check the figures they print."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from mkdocs.structure.files import File

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


def notebook_markdown(path: Path) -> str:
    """One notebook as a markdown page: markdown cells verbatim, code cells fenced."""
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    parts = []
    for cell in cells:
        text = "".join(cell["source"]).rstrip()
        if not text:
            continue
        if cell["cell_type"] == "code":
            text = f"```python\n{text}\n```"
        parts.append(text)
    source = f"`notebooks/{path.name}`"
    parts.append(f"---\n\nSource: {source}; run it with `jupyter lab {source[1:-1]}` (the test "
                 "suite executes it: `pytest -m slow tests/test_notebooks.py`).")
    return "\n\n".join(parts) + "\n"


def on_files(files, config):
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        files.append(File.generated(config, f"notebooks/{path.stem}.md",
                                    content=notebook_markdown(path)))
    return files


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
