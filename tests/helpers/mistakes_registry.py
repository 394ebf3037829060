"""The registry behind tests/docs/test_docs_mistakes_table.py: what ties a row of docs/conventions.md's "Common
mistakes" table to its proof, and how a case's outcome is judged against the row.

A row is proved in one of two ways, each keyed by a part of its "Mistake" cell:

* ``@case(key)``: a function that makes the mistake here and returns the :class:`Outcome` (the error,
  the geometry warnings, or nothing). The row's "What you see now" cell is then checked against it
  (:func:`problems`): its leading words give the kind, its double-quoted phrases (pieces split at
  ``...``) must appear in the messages.
* ``proved_by(key, "tests/...py::test_name", ...)``: for a row that needs a real framework or minutes
  (OpenPCDet, mmdetection3d), the named tests, which CI runs elsewhere, must exist: the file is parsed
  (not imported) and must define each function (:func:`proof_problems`).
"""

from __future__ import annotations

import ast
import contextlib
import io
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from mssf_blocks.errors import MSSFError, MSSFGeometryWarning

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "conventions.md"

#: the leading words of a "What you see now" cell and the kind of outcome they promise ("none": the call
#: goes through without an error or a geometry warning; what it then does is the case's own assertion)
KINDS: Tuple[Tuple[str, str], ...] = (("error", "error"), ("our error", "error"), ("warning", "warning"),
                                      ("accepted", "none"), ("no warning", "none"))


@dataclass
class Outcome:
    kind: str  # "error", "warning", "none", or "mixed [...]" when the runs of one case disagree
    messages: List[str]


class Refused(Exception):
    """A CLI run that ended as the CLI rows say: exit status 2, no traceback; the message is its last line."""


CASES: Dict[str, Callable[[], Outcome]] = {}
PROOFS: Dict[str, Tuple[str, ...]] = {}


def case(key: str):
    """Register ``fn`` for the row whose "Mistake" cell contains ``key``."""
    def register(fn):
        assert key not in CASES and key not in PROOFS, f"two proofs for {key!r}"
        CASES[key] = fn
        return fn
    return register


def proved_by(key: str, *tests: str) -> None:
    """The row whose "Mistake" cell contains ``key`` is proved by ``tests`` ("path::function", from the root)."""
    assert tests and key not in CASES and key not in PROOFS, key
    PROOFS[key] = tests


def outcome(*runs: Callable[[], object]) -> Outcome:
    """Run each mistake: each gives "error" (an ``MSSFError``, or a CLI refusal), else "warning" (geometry
    warnings, all collected) or "none". The kind is the runs' common one, "mixed" where they differ."""
    kinds: List[str] = []
    msgs: List[str] = []
    for run in runs:
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            try:
                run()
            except (MSSFError, Refused) as exc:
                kinds.append("error")
                msgs.append(str(exc))
                continue
        seen = [str(w.message) for w in got if issubclass(w.category, MSSFGeometryWarning)]
        kinds.append("warning" if seen else "none")
        msgs += seen
    return Outcome(kinds[0] if len(set(kinds)) == 1 else f"mixed {kinds}", msgs)


def cli(argv: Sequence[str]) -> None:
    """``python -m mssf_examples ARGV`` in this process: returns when it runs through, raises
    :class:`Refused` with the last stderr line when it exits with status 2 and no traceback; anything else
    (another status, a traceback) fails the test."""
    from mssf_examples.cli import commands as entry

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = entry.main(list(argv))
        except SystemExit as exc:
            code = exc.code
    text = err.getvalue()
    if code in (0, None):
        return
    assert code == 2 and "Traceback" not in text and text.strip(), (code, text)
    raise Refused(text.strip().splitlines()[-1])


# -- the table -----------------------------------------------------------------------------------------
def rows(doc: Path = DOC) -> List[Tuple[str, str]]:
    """``(mistake, what you see now)`` of every row of the first table under "## Common mistakes"."""
    text = doc.read_text().split("## Common mistakes", 1)[1].split("\n## ", 1)[0]
    lines = text.split("| Mistake | What you see now | Fix |", 1)[1].split("\n\n", 1)[0].splitlines()
    out = []
    for line in (l for l in lines if l.startswith("| ")):  # (the |---| line does not start with "| ")
        cells = [c.strip() for c in re.split(r"\|(?=(?:[^`]*`[^`]*`)*[^`]*$)", line.strip())[1:-1]]
        out.append((cells[0], cells[1]))
    return out


def keys_of(mistake: str, table) -> List[str]:
    return [k for k in table if k in mistake]


def expected_kind(seen: str) -> Optional[str]:
    """The kind a "What you see now" cell promises, by its leading words (longest match first)."""
    for words, kind in sorted(KINDS, key=lambda w: -len(w[0])):
        if seen.startswith(words):
            return kind
    return None


def phrases(seen: str) -> List[str]:
    """The quoted pieces of a cell: double-quoted phrases split at ``...``; quotes inside code spans
    (`` `backend="triton"` ``) are code, not quotations."""
    plain = re.sub(r"`[^`]*`", lambda m: m.group(0).replace('"', "'"), seen)
    return [p.strip() for q in re.findall(r'"([^"]+)"', plain) for p in q.split("...") if p.strip()]


def problems(seen: str, result: Outcome) -> List[str]:
    """Where ``result`` contradicts the cell ``seen`` (empty: the row is true)."""
    kind = expected_kind(seen)
    if kind is None:
        return [f"'What you see now' starts with none of {[w for w, _ in KINDS]}: {seen!r}"]
    out = [] if result.kind == kind else [f"the cell says {kind}, the case gave {result.kind}: {result.messages}"]
    return out + [f"{p!r} in none of {result.messages}" for p in phrases(seen)
                  if not any(p in m for m in result.messages)]


def proof_problems(test: str, root: Path = REPO) -> Optional[str]:
    """``None`` when ``test`` ("path::function" or "path::Class::function") names a test defined there."""
    path, _, name = test.partition("::")
    file = root / path
    if not name or not path.startswith("tests/") or not file.is_file():
        return f"{test}: no test file {path} (or no ::name)"
    tree = ast.parse(file.read_text(), str(file))
    *owners, func = name.split("::")
    scope: Sequence[ast.AST] = tree.body
    for owner in owners:
        found = [n for n in scope if isinstance(n, ast.ClassDef) and n.name == owner]
        if not found:
            return f"{test}: no class {owner} in {path}"
        scope = found[0].body
    if not any(isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name == func for n in scope):
        return f"{test}: {path} defines no test {func}"
    if not func.startswith("test"):
        return f"{test}: {func} is not a test pytest collects"
    return None
