"""mkdocs hook: repository files that the docs link to outside ``docs/`` become part of the site.

The pages link to files beside ``docs/`` with plain relative links (``../benchmarks/README.md``,
the reproduction page's ``../benchmarks/results/paper/.../learning_curves.png``), so that they
work when the Markdown is read on a forge. A strict build would refuse those links: they leave
the docs folder. This hook adds every such file to the site under ``repo/<its path>`` (a
Markdown file as a page, any other file copied as it is) and rewrites the links to it. Links
inside ``docs/`` are left alone, so mkdocs still checks them strictly. A link to a folder (the
reproduction page's per-seed folders) is written as the folder's repository path in code.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

PREFIX = "repo"
# [text](target) and ![alt](target); the target stops at whitespace or ')'.
_LINK = re.compile(r"(!?\[(?P<text>[^\]]*)\])\((?P<target>[^)\s]+)\)")


def _roots(config: Any) -> tuple[Path, Path]:
    docs = Path(config["docs_dir"]).resolve()
    repo = Path(config["config_file_path"]).resolve().parent
    return docs, repo


def _is_relative(target: str) -> bool:
    return not (
        target.startswith(("#", "/", "mailto:")) or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target)
    )


def _outside_targets(source: Path, text: str, docs: Path, repo: Path) -> set[Path]:
    """Files of the repository, outside ``docs/``, that ``text`` (read from ``source``) links to."""
    found = set()
    for match in _LINK.finditer(text):
        target = match["target"].split("#", 1)[0]
        if not target or not _is_relative(target):
            continue
        path = (source.parent / target).resolve()
        if path.is_file() and repo in path.parents and docs not in path.parents:
            found.add(path)
    return found


def on_files(files: Files, config: Any) -> Files:
    docs, repo = _roots(config)
    pending = [Path(f.abs_src_path) for f in files if f.src_uri.endswith(".md") and f.abs_src_path]
    added: set[Path] = set()
    while pending:  # pages added from outside may link further (benchmarks/README.md)
        source = pending.pop()
        for path in _outside_targets(source, source.read_text(encoding="utf-8"), docs, repo):
            if path in added:
                continue
            added.add(path)
            src_uri = posixpath.join(PREFIX, path.relative_to(repo).as_posix())
            files.append(File.generated(config, src_uri, abs_src_path=str(path)))
            if path.suffix == ".md":
                pending.append(path)
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    docs, repo = _roots(config)
    source = Path(page.file.abs_src_path).resolve()
    page_dir = posixpath.dirname(page.file.src_uri)

    def site_uri(path: Path) -> str | None:
        if docs == path or docs in path.parents:
            return path.relative_to(docs).as_posix()
        if repo in path.parents:
            return posixpath.join(PREFIX, path.relative_to(repo).as_posix())
        return None

    def rewrite(match: re.Match[str]) -> str:
        target, _, anchor = match["target"].partition("#")
        if not target or not _is_relative(target):
            return match[0]
        path = (source.parent / target).resolve()
        if docs in source.parents and (docs == path or docs in path.parents):
            return match[0]  # a link inside docs/: mkdocs checks it
        if path.is_dir() and repo in path.parents:
            return f"`{path.relative_to(repo).as_posix()}/`"
        uri = site_uri(path)
        if uri is None or files.get_file_from_path(uri) is None:
            return match[0]  # left for mkdocs to report
        link = posixpath.relpath(uri, page_dir or ".")
        return f"{match[1]}({link}{'#' + anchor if anchor else ''})"

    return _LINK.sub(rewrite, markdown)
