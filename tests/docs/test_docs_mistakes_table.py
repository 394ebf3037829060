"""docs/conventions.md, "Common mistakes": every row of the table is proved, and each proof is run or found.

Each row's "Mistake" cell is matched by exactly one key (a part of that cell) of one of two registries
(tests/helpers/mistakes_registry.py):

* a **case** (tests/helpers/mistakes_geometry.py, mistakes_library.py, mistakes_cli.py, mistakes_more.py) makes
  the mistake and returns what the library did: the ``MSSFError`` (or the CLI's one line with exit status 2), the
  ``MSSFGeometryWarning`` s, or nothing. The row's "What you see now" cell decides: one that starts with
  "error" (or "our error") needs an error from every mistake the case runs, "warning" a warning and no
  error, "accepted" / "no warning" neither (what then works is the case's own assertion); and every
  double-quoted phrase in it (pieces split at ``...``) must appear in one of the messages.
* a **proof** (tests/helpers/mistakes_frameworks.py) names the framework tests that prove the row (they need
  OpenPCDet / mmdetection3d and take seconds to minutes): each must exist, as a test function of its file.

A row without either fails, and so does a key that matches no row. Adding a case is one function::

    @case("FPN levels coarsest first")
    def _():
        return outcome(lambda: ...)   # runs the mistake, records the error or the warnings
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import mistakes_cli  # noqa: E402,F401  (each registers its cases)
import mistakes_frameworks  # noqa: E402,F401
import mistakes_geometry  # noqa: E402,F401
import mistakes_library  # noqa: E402,F401
import mistakes_more  # noqa: E402,F401
from mistakes_registry import (CASES, PROOFS, Outcome, keys_of, problems, proof_problems,  # noqa: E402
                               rows)

pytestmark = pytest.mark.usefixtures("one_thread")


def test_every_row_has_one_case_or_proof():
    missing, ambiguous = [], []
    for mistake, _ in rows():
        keys = keys_of(mistake, CASES) + keys_of(mistake, PROOFS)
        (missing if not keys else ambiguous if len(keys) > 1 else []).append(mistake)
    assert not missing, f"rows without a case or a proof (add a @case or a proved_by): {missing}"
    assert not ambiguous, f"rows matched by several keys: {ambiguous}"
    stale = [k for k in list(CASES) + list(PROOFS) if not any(k in m for m, _ in rows())]
    assert not stale, f"keys of no row: {stale}"


@pytest.mark.parametrize("mistake,seen", [r for r in rows() if keys_of(r[0], CASES)], ids=lambda v: v[:40])
def test_row_does_what_it_says(mistake, seen):
    result = CASES[keys_of(mistake, CASES)[0]]()
    assert not problems(seen, result), (mistake, problems(seen, result))


@pytest.mark.parametrize("mistake", [m for m, _ in rows() if keys_of(m, PROOFS)], ids=lambda v: v[:40])
def test_row_is_proved_by_tests_that_exist(mistake):
    found = [proof_problems(t) for t in PROOFS[keys_of(mistake, PROOFS)[0]]]
    assert not any(found), [f for f in found if f]


# -- the walker itself can fail ---------------------------------------------------------------------
def test_a_case_sees_a_correct_call_as_quiet():
    """Correct inputs give kind "none" (so a "warning" verdict means something)."""
    import test_first_call as fc
    from mistakes_registry import outcome

    vox, pts, pb, l2i, size = fc.scene()
    assert outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, size)).kind == "none"


def test_a_wrong_kind_or_phrase_is_a_problem():
    said = 'error: "expected levels finest first ... reversed (coarsest first)?"'
    msg = "image_features: expected levels finest first (...); reversed (coarsest first)? pass them"
    assert problems(said, Outcome("error", [msg])) == []
    assert problems(said.replace("reversed (coarsest first)?", "reversed?"), Outcome("error", [msg]))
    assert problems(said, Outcome("warning", [msg])) and problems(said, Outcome("mixed ['error', 'none']", [msg]))
    assert problems("(nothing: it works)", Outcome("none", []))  # no leading kind word
    # quotes inside code spans are code, not phrases to find
    assert problems('error naming both versions, `backend="triton"`', Outcome("error", ["3.0 and 2.1"])) == []


def test_a_proof_naming_a_missing_test_is_a_problem():
    real = "tests/integrations/test_openpcdet_data_checks.py::test_4_float_points_whose_size_divides_by_7_are_refused"
    assert proof_problems(real) is None
    assert proof_problems(real + "_renamed")
    assert proof_problems(real.replace("data_checks", "data_check"))
    assert proof_problems("tests/helpers/mistakes_registry.py::proof_problems")  # defined, but not a test
