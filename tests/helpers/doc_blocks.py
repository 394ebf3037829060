"""Reading and running the ```python blocks of README.md and docs/*.md (``test_docs_snippets.py`` classifies
and runs them, ``test_docs_references.py`` checks the API signature listings among them).

A block is keyed by ``(file, first code line)``; :func:`exec_block` runs its text exactly as written,
with the doc file as the code's filename (a traceback points into the docs), then re-evaluates every
line that shows a tensor in a comment (``expr   # tensor([[ 5.0000, ...]])``) and compares it with the
shown value to its printed precision.
"""

from __future__ import annotations

import re
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch

REPO = Path(__file__).resolve().parents[2]
DOC_FILES = [REPO / "README.md"] + sorted((REPO / "docs").glob("*.md"))


# ---------------------------------------------------------------------------------------------------
# reading the blocks
# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Block:
    file: str  # relative to the repository, e.g. "docs/fusion.md"
    index: int  # 0-based among the file's python blocks
    line: int  # 1-based line of the opening fence
    code: str

    @property
    def first_line(self) -> str:
        return next(l.strip() for l in self.code.splitlines() if l.strip())

    @property
    def key(self) -> Tuple[str, str]:
        return (self.file, self.first_line)

    @property
    def id(self) -> str:
        return f"{self.file}#{self.index}:{self.first_line[:40]}"


_FENCE = re.compile(r"^(\s*)(```+)\s*([\w+-]*)")


def python_blocks(path: Path) -> List[Block]:
    """The fenced ```python blocks of a Markdown file (indented fences included, body dedented)."""
    blocks, lines = [], path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang, start = m.group(2), m.group(3).lower(), i
        i += 1
        body = []
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i])
            i += 1
        i += 1  # the closing fence
        if lang in ("python", "py", "python3"):
            rel = path.relative_to(REPO).as_posix()
            count = sum(b.file == rel for b in blocks)
            blocks.append(Block(rel, count, start + 1, textwrap.dedent("\n".join(body)) + "\n"))
    return blocks


ALL_BLOCKS = [b for f in DOC_FILES for b in python_blocks(f)]
BLOCKS_BY_KEY: Dict[Tuple[str, str], Block] = {b.key: b for b in ALL_BLOCKS}


# ---------------------------------------------------------------------------------------------------
# running a block
# ---------------------------------------------------------------------------------------------------
def exec_block(block: Block, namespace: Dict[str, object], insert: Optional[Dict[str, str]] = None) -> Dict[str, object]:
    """Run ``block`` in ``namespace`` (modified in place and returned).

    ``insert`` maps a line of the block (stripped) to code run just before it: names the block's own
    later lines assume but only exist after its earlier lines ran (e.g. the backbone's ``stage``).
    """
    code = block.code
    for marker, extra in (insert or {}).items():
        lines = code.splitlines()
        hits = [i for i, l in enumerate(lines) if l.strip() == marker]
        assert len(hits) == 1, f"{block.id}: expected the line {marker!r} once, found it {len(hits)} times"
        lines[hits[0]:hits[0]] = [extra]
        code = "\n".join(lines) + "\n"
    namespace.setdefault("__name__", "__doc_snippet__")
    exec(compile(code, f"{block.file} (python block {block.index}, line {block.line})", "exec"), namespace)
    namespace["__shown_tensors_checked__"] = check_shown_tensors(block, namespace)
    return namespace


_SHOWN_TENSOR = re.compile(r"^(?P<expr>[^#]+?)\s*#\s*(?P<out>tensor\(.*\))\s*$")


def check_shown_tensors(block: Block, namespace: Dict[str, object]) -> int:
    """Lines ``expr  # tensor([...])``: ``expr`` evaluates to the shown tensor, to its printed digits.

    Returns the number of lines checked.
    """
    checked = 0
    for line in block.code.splitlines():
        m = _SHOWN_TENSOR.match(line.strip())
        if not m:
            continue
        got = eval(m.group("expr"), namespace)
        shown = eval(m.group("out"), {"tensor": lambda data, **_: torch.tensor(data, dtype=torch.float64)})
        decimals = [len(d) for d in re.findall(r"\d\.(\d+)", m.group("out"))]
        atol = 0.5 * 10.0 ** -max(decimals) if decimals else 0.0
        assert tuple(got.shape) == tuple(shown.shape), f"{block.id}: {line.strip()!r} gives shape {tuple(got.shape)}"
        torch.testing.assert_close(got.to(torch.float64), shown.to(torch.float64), atol=atol * 1.0001, rtol=0,
                                   msg=lambda msg: f"{block.id}: {line.strip()!r} shows a different value:\n{msg}")
        checked += 1
    return checked
