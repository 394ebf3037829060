"""mkdocs hook (mkdocs.yml ``hooks:``): links from docs/ to repository files outside docs/.

A page may link to ``../examples/quickstart.py`` or ``../README.md``: relative, so the link works when
the Markdown is read on GitHub or in a clone. mkdocs only knows files under ``docs_dir`` and would
report such a link as broken. This hook resolves each one against the repository: an existing target
becomes a link to it in ``repo_url`` (``blob/main/...``, ``tree/main/...`` for a folder); a missing one
aborts the build, so broken links still fail ``mkdocs build --strict``.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.exceptions import PluginError

_LINK = re.compile(r"(\]\()([^)\s#]+)(#[^)\s]*)?((?:\s+\"[^\"]*\")?\))")
_FENCE = re.compile(r"^(\s*)(```+|~~~+)", re.M)


def _outside_links(text: str, page_dir: str, repo: Path, docs: str, base: str, where: str) -> str:
    def fix(m: re.Match) -> str:
        target = m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("/"):
            return m.group(0)  # a URL or an absolute path: not ours to resolve
        rel = posixpath.normpath(posixpath.join(docs, page_dir, target))
        if rel == docs or rel.startswith(docs + "/"):
            return m.group(0)  # inside docs/: mkdocs checks it
        if rel.startswith(".."):
            raise PluginError(f"{where}: link {target!r} leaves the repository")
        path = repo / rel
        if not path.exists():
            raise PluginError(f"{where}: link {target!r} points to {rel}, which does not exist")
        kind = "tree" if path.is_dir() else "blob"
        return f"{m.group(1)}{base}/{kind}/main/{rel}{m.group(3) or ''}{m.group(4)}"

    return _LINK.sub(fix, text)


def on_page_markdown(markdown: str, page, config, files) -> str:
    repo = Path(config["config_file_path"]).resolve().parent
    docs = Path(config["docs_dir"]).resolve().relative_to(repo).as_posix()
    base = str(config.get("repo_url") or "").rstrip("/")
    page_dir = posixpath.dirname(page.file.src_uri)
    # only the prose: fenced code blocks stay as written
    parts, pos, in_code, fence = [], 0, False, ""
    for m in _FENCE.finditer(markdown):
        if not in_code:
            parts.append(_outside_links(markdown[pos:m.start()], page_dir, repo, docs, base, page.file.src_uri))
            pos, in_code, fence = m.start(), True, m.group(2)[:3]
        elif m.group(2).startswith(fence):
            line_end = markdown.find("\n", m.end())
            end = len(markdown) if line_end < 0 else line_end
            parts.append(markdown[pos:end])
            pos, in_code = end, False
    tail = markdown[pos:]
    parts.append(tail if in_code else _outside_links(tail, page_dir, repo, docs, base, page.file.src_uri))
    return "".join(parts)
