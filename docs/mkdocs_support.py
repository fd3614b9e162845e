"""Two adaptations that let ``mkdocs build --strict`` render this repository (not a page of the site).

- A griffe extension: ``envs/`` installs as ``l1flow_rl.envs`` (``package-dir`` in pyproject.toml),
  which griffe, reading the source tree, cannot see under ``l1flow_rl/``; it loads that folder as the
  package's ``envs`` member so the API pages can render it under its import name.
- The same extension shows the docstrings' Sphinx roles (``:class:`~l1flow_rl.L1FlowActor```, as editors
  and Sphinx read them) as code, ``L1FlowActor``, since the Google-style renderer
  would print them as they are written.
- A mkdocs hook: the guides link to repository files outside ``docs/`` (``benchmarks/RESULTS.md``),
  which the repository's web view opens and a built site cannot. Each such link must name a file
  that exists (else the build fails, as for any broken link); the site shows it as its path.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import griffe

_ROOT = Path(__file__).resolve().parent.parent
# folders that install inside l1flow_rl from elsewhere in the repository (pyproject.toml's package-dir)
_INSTALLED_INSIDE = {"envs": _ROOT / "envs"}
_log = logging.getLogger("mkdocs.plugins.l1flow_rl")


_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const):`(?P<tilde>~?)(?P<name>[^`]+)`")


def _role_as_code(match: re.Match[str]) -> str:
    name = match["name"].rsplit(".", 1)[-1] if match["tilde"] else match["name"]
    return f"`{name}`"


class InstalledSubpackages(griffe.Extension):
    """Attach the folders that install inside ``l1flow_rl`` from elsewhere (``envs/``), and show
    Sphinx roles in docstrings as code."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_role_as_code, obj.docstring.value)

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        if pkg.name != "l1flow_rl":
            return
        for name, folder in _INSTALLED_INSIDE.items():
            if name in pkg.members:
                continue
            # loaded into the same collections, so that its aliases resolve through the package
            sub = griffe.load(
                name,
                search_paths=[folder.parent],
                docstring_parser=loader.docstring_parser,
                docstring_options=loader.docstring_options,
                modules_collection=loader.modules_collection,
                lines_collection=loader.lines_collection,
                extensions=loader.extensions,
            )
            loader.modules_collection.del_member(name)  # a member of the package, not a top level
            pkg.set_member(name, sub)


_LINK = re.compile(r"\[(?P<text>[^\]]+)\]\((?P<target>(?!https?:|mailto:|#)[^)\s#]+)(?P<anchor>#[^)\s]*)?\)")


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Rewrite links that leave ``docs/`` into the path of the repository file they name."""
    docs = Path(config["docs_dir"]).resolve()
    page_dir = (docs / page.file.src_uri).parent

    def outside(match: re.Match[str]) -> str:
        target = (page_dir / match["target"]).resolve()
        if target.is_relative_to(docs):
            return match[0]
        if not target.exists():
            _log.warning("%s links to %s, which is not in the repository", page.file.src_uri, match["target"])
            return match[0]
        path = target.relative_to(_ROOT).as_posix()
        text = match["text"]
        return text if text.strip("`") == path else f"{text} (`{path}`)"

    return _LINK.sub(outside, markdown)
