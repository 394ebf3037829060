"""The checks every block kind gets, written once: one base class, one subclass per block kind.

After kornia's ``testing/base.py`` (``BaseTester``) and torchvision's ``RoIOpTester``: a subclass says how
to build its block, the block's inputs and an independent reference (the hooks below); the base class
holds the checks themselves, so each is written, and kept strict, in one place:

* ``test_matches_reference[device-case]``: the block on every device of ``tests/conftest.py``'s ``device``
  fixture (the CPU, and CUDA where ``torch.cuda.is_available()``) against a reference computed on the CPU,
  compared on the CPU with :func:`mssf_blocks.testing.assert_close` (the tolerance of the less precise
  dtype: 1e-10 for float64 against float64);
* ``test_gradcheck64[case]``: ``torch.autograd.gradcheck`` in float64 (:func:`mssf_blocks.testing.gradcheck64`);
* ``test_state_dict_round_trip``: a second block, built the same way, loaded from the first one's
  ``state_dict`` holds the same tensors and gives the same outputs, bit for bit;
* ``test_compile_smoke[case]``: ``torch.compile(fullgraph=True, backend="eager")`` of the reference run gives
  the eager outputs (float64 tolerance), for the block kinds ``tests/test_compile.py`` compiles (its
  recompilation, training-mode and gradient checks stay there).

Hooks (a check whose hook a subclass leaves ``None`` is not generated for that kind: no test, no skip):

* ``reference_cases``: ``{id: param}``; ``reference(param) -> Reference``;
* ``gradcheck_cases``: ``{id: param}``; ``gradcheck(param) -> (fn, inputs)``;
* ``state_dict_case() -> (build, run)``: ``build()`` a fresh block (its own random initialisation),
  ``run(block)`` its outputs;
* ``compile_smoke = True``: the compile check, on ``compile_cases`` (``{id: reference param}``; by default
  the first reference case).

The cases are parametrised by the class's ``pytest_generate_tests`` (pytest calls it for the methods of a
test class), so a subclass lists its cases as data and inherits the test functions.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Sequence, Tuple

import pytest
import torch
from torch import nn

from mssf_blocks import torch_versions as _compat
from mssf_blocks.testing import assert_close, gradcheck64

# the hooks each generated check needs (a subclass without the hook gets no such test)
_NEEDS = {
    "test_matches_reference": "reference",
    "test_gradcheck64": "gradcheck",
    "test_state_dict_round_trip": "state_dict_case",
    "test_compile_smoke": "compile_smoke",
}


@dataclass
class Reference:
    """One reference case: ``inputs(device)`` builds the block's inputs on ``device`` (a tuple), ``run(block,
    *inputs)`` gives its outputs (a tensor or a tuple of them); ``expected`` (same structure) was computed
    independently on the CPU."""

    module: nn.Module
    inputs: Callable[[torch.device], Tuple]
    run: Callable[..., Any]
    expected: Any


def _as_tuple(x) -> Tuple:
    return tuple(x) if isinstance(x, (tuple, list)) else (x,)


class BlockTester:
    """Base of the per-block-kind test classes (``class TestSFF(BlockTester)``); see the module docstring."""

    reference_cases: Dict[str, Any] = {"default": None}
    gradcheck_cases: Dict[str, Any] = {"default": None}
    reference: Optional[Callable[..., Reference]] = None
    gradcheck: Optional[Callable[..., Tuple[Callable, Sequence]]] = None
    state_dict_case: Optional[Callable[[], Tuple[Callable, Callable]]] = None
    compile_smoke: bool = False
    #: the reference cases the compile smoke runs (``None``: the first one; compiling is the slow part)
    compile_cases: Optional[Dict[str, Any]] = None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        for test, hook in _NEEDS.items():
            if not getattr(cls, hook):
                setattr(cls, test, None)  # not collected: pytest only collects functions

    def pytest_generate_tests(self, metafunc):
        if "case" not in metafunc.fixturenames:
            return
        name = metafunc.function.__name__
        cases = self.reference_cases
        if name == "test_gradcheck64":
            cases = self.gradcheck_cases
        elif name == "test_compile_smoke":
            cases = self.compile_cases or dict([next(iter(self.reference_cases.items()))])
        metafunc.parametrize("case", list(cases.values()), ids=list(cases))

    # -- the checks -------------------------------------------------------------------------------------
    def assert_outputs_close(self, got, expected) -> None:
        got, expected = _as_tuple(got), _as_tuple(expected)
        assert len(got) == len(expected), (len(got), len(expected))
        for i, (g, e) in enumerate(zip(got, expected)):
            assert_close(g.detach().cpu(), e, msg=f"output {i}")

    def test_matches_reference(self, case, device):
        ref = self.reference(case)
        out = ref.run(ref.module.to(device), *ref.inputs(device))
        self.assert_outputs_close(out, ref.expected)

    def test_gradcheck64(self, case):
        fn, inputs = self.gradcheck(case)
        assert gradcheck64(fn, inputs)

    def test_state_dict_round_trip(self):
        build, run = self.state_dict_case()
        a, b = build(), build()
        state = a.state_dict()
        # two builds differ (their own random draws), so what makes them equal below is the load
        assert any(not torch.equal(t, state[k]) for k, t in b.state_dict().items() if t.is_floating_point())
        b.load_state_dict(state)
        assert b.state_dict().keys() == state.keys()
        for name, tensor in b.state_dict().items():
            assert torch.equal(tensor, state[name]), name
        got, want = _as_tuple(run(b)), _as_tuple(run(a))
        assert len(got) == len(want)
        for x, y in zip(got, want):
            assert torch.equal(x, y)

    def test_compile_smoke(self, case):
        missing = _compat.missing("compile_dynamic")
        if missing is not None:  # as tests/test_compile.py: the floor's dynamo cannot capture the blocks' checks
            pytest.skip(str(missing))
        import torch._dynamo

        ref = self.reference(case)
        inputs = ref.inputs(torch.device("cpu"))
        eager = ref.run(copy.deepcopy(ref.module), *inputs)
        torch._dynamo.reset()
        compiled = torch.compile(ref.run, fullgraph=True, backend="eager")
        got, eager = _as_tuple(compiled(copy.deepcopy(ref.module), *inputs)), _as_tuple(eager)
        assert len(got) == len(eager)
        for g, e in zip(got, eager):
            torch.testing.assert_close(g, e, rtol=1e-10, atol=1e-10)
