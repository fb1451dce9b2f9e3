"""An mkdocs hook: the examples in the built site, and the pages' links to them.

```
 examples/**/*.py, *.toml ──on_files──► the site's examples/... (the files as they are)
 a page's [text](../../examples/x.py)  ──on_page_markdown──► [text](../examples/x.py)
   (the file in the repository,               (its copy in the site: mkdocs checks the
    where GitHub and a checkout find it)        link, --strict, and writes its URL)
```

A page shows an example's text through a snippet include (`--8<-- "examples/x.py"`),
which only the built site renders; a reader of the page in the repository (GitHub, an
editor) sees the include line. So a page also links to the file, by its path in the
repository, relative to the page: that link works there as written, and here it is
turned into a link to the copy of the file that `on_files` puts into the site. mkdocs
refuses a link out of `docs/` (`--strict`), and the project has no URL of its own to
link to. Listed under `hooks:` in `mkdocs.yml`; `tests/test_docs.py` builds the site
and follows the links.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

EXAMPLES = "examples"
"""The folder, at the top of the repository, whose files go into the site at the same path."""

SUFFIXES = (".py", ".toml")
"""What of it: the programs, and the plans the how-tos include."""

LINK = re.compile(r"\]\((?P<target>[^)\s#]+)(?P<anchor>#[^)\s]*)?\)")
"""An inline Markdown link's target (`[text](target#anchor)`)."""


def _repository(config: Any) -> Path:
    return Path(config.config_file_path).resolve().parent


def on_files(files: Files, *, config: Any) -> Files:
    """Add every example to the site, at `examples/...` as in the repository."""
    examples = _repository(config) / EXAMPLES
    for path in sorted(examples.rglob("*")):
        if path.suffix in SUFFIXES and "__pycache__" not in path.parts:
            uri = path.relative_to(examples.parent).as_posix()
            files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


def on_page_markdown(markdown: str, *, page: Any, config: Any, files: Files) -> str:
    """Turn each link to an example in the repository into one to its copy in the site."""
    del files
    source = Path(page.file.abs_src_path).resolve().parent  # the page's folder in docs/
    examples = _repository(config) / EXAMPLES
    docs = Path(config.docs_dir).resolve()

    def to_site(link: re.Match[str]) -> str:
        target = link.group("target")
        if "://" in target:
            return link.group(0)
        path = (source / target).resolve()
        if not (path.is_relative_to(examples) and path.is_file()):
            return link.group(0)
        copy = docs / path.relative_to(examples.parent)  # where the site has it, as a source
        relative = Path(os.path.relpath(copy, source)).as_posix()
        return f"]({relative}{link.group('anchor') or ''})"

    return LINK.sub(to_site, markdown)
