"""What the docs say about the code beyond runnable blocks: every API signature listing (a ```python block
classified as such in ``test_docs_snippets.py``) names the parameters, in order, and the literal
defaults of the code; every ``python examples/...py`` / ``python benchmarks/...py`` they mention exists.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import List

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from doc_blocks import ALL_BLOCKS, DOC_FILES, REPO  # noqa: E402
from test_docs_snippets import _SIGNATURES, FRAGMENTS  # noqa: E402 - the classification of the blocks


_SIGNATURE_START = re.compile(r"^([ \t]*)(\.?)(\w+)\(", re.M)
_SIGNATURE_MODULES = ("mssf_blocks", "mssf_blocks.diagnostics", "mssf_blocks.samplers", "mssf_blocks.heads",
                      "mssf_blocks.lift", "mssf_blocks.functional.lift", "mssf_blocks.functional.sampling",
                      "mssf_blocks.functional.deform")


def _top_level_split(text: str) -> List[str]:
    depth, cur, out = 0, "", []
    for ch in text:
        depth += {"(": 1, "[": 1, "{": 1, ")": -1, "]": -1, "}": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    return [a.strip() for a in out + [cur] if a.strip()]


def documented_signatures(code: str):
    """``(owner, name, [(param, default text or None)])`` per ``name(...)`` of a signature listing.

    A name at column 0 is a module-level function or class; an indented ``name(`` / ``.name(`` (or a
    column-0 name the modules lack) is a method of the last class listed above it.
    """
    import importlib
    import inspect

    modules = [importlib.import_module(m) for m in _SIGNATURE_MODULES]
    code = re.sub(r"#[^\n]*", "", code)
    cls, out = None, []
    for m in _SIGNATURE_START.finditer(code):
        indent, dot, name = m.groups()
        j, depth = m.end(), 1
        while depth:
            depth += {"(": 1, ")": -1}.get(code[j], 0)
            j += 1
        params = []
        for arg in _top_level_split(code[m.end():j - 1]):
            head, _, default = arg.partition("=")
            params.append((re.match(r"\w+", head).group(0), default.strip() or None))
        # (a submodule named like a function, mssf_blocks.lift.pillar_lift beside functional.lift.pillar_lift, is not it)
        top = next((getattr(mod, name) for mod in modules
                    if hasattr(mod, name) and not inspect.ismodule(getattr(mod, name))), None)
        if not indent and not dot and top is not None:
            obj, cls = top, (top if isinstance(top, type) else None)
        else:
            assert cls is not None and hasattr(cls, name), f"{name}(...) is neither in {_SIGNATURE_MODULES} nor a method of {cls}"
            obj = getattr(cls, name)
        out.append((obj, name, params))
    return out


SIGNATURE_BLOCKS = [b for b in ALL_BLOCKS if FRAGMENTS.get(b.key) == _SIGNATURES]


@pytest.mark.parametrize("block", SIGNATURE_BLOCKS, ids=[b.id for b in SIGNATURE_BLOCKS])
def test_signature_listing_matches_the_code(block):
    """Listed parameter names (in order) and literal defaults are those of the code."""
    import ast
    import inspect

    listed = documented_signatures(block.code)
    assert listed, f"{block.id}: no signature found"
    for obj, name, params in listed:
        real = {k: p for k, p in inspect.signature(obj).parameters.items() if k != "self"}
        assert [p for p, _ in params] == list(real), f"{block.id}: {name}{tuple(p for p, _ in params)} vs code {tuple(real)}"
        for param, default in params:
            if default is None:
                continue
            try:
                value = ast.literal_eval(default)
            except ValueError:
                try:
                    value = eval(default, {"nn": torch.nn})
                except Exception:  # e.g. '"mean" | "count"': a choice, not a value
                    continue
            assert real[param].default == value, f"{block.id}: {name}({param}={default}) but the code has {real[param].default!r}"


_SCRIPT = re.compile(r"\bpython3?\s+((?:examples|benchmarks)/[\w./-]+\.py)\b")


def test_mentioned_scripts_exist():
    """Every ``python examples/...py`` / ``python benchmarks/...py`` in README.md and docs/*.md exists."""
    mentioned = {(f.relative_to(REPO).as_posix(), m) for f in DOC_FILES for m in _SCRIPT.findall(f.read_text(encoding="utf-8"))}
    assert mentioned, "found no script mention at all: the pattern is broken"
    missing = sorted((f, m) for f, m in mentioned if not (REPO / m).is_file())
    assert not missing, f"scripts mentioned in the docs that do not exist: {missing}"
