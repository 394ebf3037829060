"""MSDFF through the shared block checks (``tests/helpers/block_tester.py``): every method and value
projection against ``fusion_references`` (every pixel projected with ``value_proj``, then per-level
``F.grid_sample``) on every device, the default initialisation's uniform attention, float64 gradcheck, the
state-dict round trip and a compile smoke. MSDFF's other behaviour: ``test_msdff.py``."""

import itertools

import pytest
import torch

from mssf_blocks.samplers import MSDFF

from block_tester import BlockTester, Reference
from fusion_references import D64, WIDTHS, make_projection, randomize_msdff, randomize_norm, reference_msdff, scene, width_kw

# Tiny tensors: with 2 OpenMP threads on a loaded 2-core machine, each train-mode batch_norm call
# spins for ~10-50 ms (measured), which makes gradcheck 100x slower. One thread is plenty here.
pytestmark = pytest.mark.usefixtures("one_thread")

_WIDTHS = [p.values[0] for p in WIDTHS]  # "paper", "narrow"
_METHODS = [("auto", "after_sampling"), ("reference", "after_sampling"), ("fast", "after_sampling"),
            ("fast", "before_sampling"), ("reference", "before_sampling")]


def _sample_then_project(method, value_projection, width):
    # sample then project (the module) equals project then sample (the reference), with samples partly
    # outside the image
    gen = torch.Generator().manual_seed(7)
    levels, uv, valid, bidx = scene(gen, chans=(4, 4), sizes=((5, 6), (3, 4)))
    uv[3] = torch.tensor([0.02, 0.97], dtype=D64)  # near the border: samples partly outside (mass < 1)
    valid[3] = True
    mod = MSDFF(4, 8, num_heads=2, num_levels=2, num_points=3, method=method,
                value_projection=value_projection, dtype=D64, **width_kw(width, 8)).eval()
    assert mod.value_proj.weight.shape == ((4, 4) if width == "paper" else (8, 4))
    randomize_msdff(mod, gen)
    query = torch.randn(7, 8, generator=gen, dtype=D64)
    want, off, _ = reference_msdff(mod, query, levels, uv, valid, bidx)
    # Make sure the bias-times-mass term matters: some sampling location reads outside the image.
    sizes = torch.tensor([[6.0, 5.0], [4.0, 3.0]], dtype=D64)
    loc = uv[3, 0] + off[3] / sizes[None, :, None, :]
    pix = loc * sizes[None, :, None, :] - 0.5
    assert ((pix < 0) | (pix > sizes[None, :, None, :] - 1)).any()
    return Reference(mod, lambda d: (query.to(d), [l.to(d) for l in levels], make_projection(uv, valid, bidx, d)),
                     lambda m, q, lv, proj: m(q, lv, proj), want)


def _default_init(width):
    gen = torch.Generator().manual_seed(8)
    levels, uv, valid, bidx = scene(gen, v=1, chans=(4, 4))
    mod = MSDFF(4, 8, num_heads=4, num_levels=2, num_points=2, dtype=D64, **width_kw(width, 8)).eval()
    randomize_norm(mod.norm, gen)
    query = torch.randn(7, 8, generator=gen, dtype=D64)
    want, _, att = reference_msdff(mod, query, levels, uv, valid, bidx)
    assert torch.allclose(att, torch.full_like(att, 0.25))  # zero-initialised attention: uniform
    return Reference(mod, lambda d: (query.to(d), [l.to(d) for l in levels], make_projection(uv, valid, bidx, d)),
                     lambda m, q, lv, proj: m(q, lv, proj), want)


class TestMSDFF(BlockTester):
    reference_cases = {
        **{f"{method}-{vp}-{width}_width": ("sample_then_project", method, vp, width)
           for width, (method, vp) in itertools.product(_WIDTHS, _METHODS)},
        **{f"default_init-{width}_width": ("default_init", width) for width in _WIDTHS},
    }
    gradcheck_cases = {f"{vp}-{width}_width": (vp, width)
                       for width, vp in itertools.product(_WIDTHS, ["after_sampling", "before_sampling"])}
    compile_cases = {"auto-after_sampling-paper_width": ("sample_then_project", "auto", "after_sampling", "paper")}
    compile_smoke = True

    def reference(self, case):
        kind, *args = case
        return _sample_then_project(*args) if kind == "sample_then_project" else _default_init(*args)

    def gradcheck(self, case):
        # Eval-mode BN (a fixed affine map) with random running statistics; sampling offsets and attention
        # weights are randomised so the gradient w.r.t. the query goes through locations and softmax.
        value_projection, width = case
        gen = torch.Generator().manual_seed(9)
        levels, uv, valid, bidx = scene(gen, n=4, chans=(2, 2), sizes=((4, 5), (2, 3)))
        mod = MSDFF(2, 4, num_heads=2, num_levels=2, num_points=2, value_projection=value_projection, dtype=D64,
                    **width_kw(width, 4)).eval()
        randomize_msdff(mod, gen, scale=0.3)
        query = torch.randn(4, 4, generator=gen, dtype=D64)

        def fn(q, l0, l1, uv_):
            return mod(q, [l0, l1], make_projection(uv_, valid, bidx))

        return fn, (query, levels[0], levels[1], uv)

    def state_dict_case(self):
        gen = torch.Generator().manual_seed(10)
        levels, uv, valid, bidx = scene(gen, chans=(4, 4), sizes=((5, 6), (3, 4)))
        query = torch.randn(7, 8, generator=gen, dtype=D64)

        def build():
            mod = MSDFF(4, 8, num_heads=2, num_levels=2, num_points=3, dtype=D64).eval()
            randomize_msdff(mod, gen)  # every projection and the norm of its own (next draws of gen)
            return mod

        return build, lambda m: m(query, levels, make_projection(uv, valid, bidx))
