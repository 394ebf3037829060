"""mssf_blocks.torch_versions: the torch-version shims give the same results on every torch, and a missing feature
is refused with the torch version it needs. Runs in every environment of `make test-compat`."""

import re

import pytest
import torch

from mssf_blocks import MSSFError, torch_versions as _compat


def test_missing_feature_is_refused_naming_the_versions(monkeypatch):
    version, what, _ = _compat.FEATURES["export_dynamic_shapes"]
    monkeypatch.setitem(_compat.FEATURES, "export_dynamic_shapes", (version, what, lambda: False))
    with pytest.raises(MSSFError, match=rf"graph_dynamic_shapes: .*needs torch >= {re.escape(version)}; "
                                        rf"this is torch {re.escape(torch.__version__)}$"):
        _compat.require("export_dynamic_shapes", "graph_dynamic_shapes")
    monkeypatch.setitem(_compat.FEATURES, "export_dynamic_shapes", (version, what, lambda: True))
    assert _compat.missing("export_dynamic_shapes") is None
    _compat.require("export_dynamic_shapes")


def test_unknown_feature_is_an_error():
    with pytest.raises(MSSFError, match="feature: expected one of .*got 'jit_magic'"):
        _compat.has("jit_magic")


@pytest.mark.parametrize("workaround", [False, True])
def test_embedding_bag_weight_gradient_equals_a_loop(monkeypatch, workaround):
    """The per-sample weights' gradient with a table that needs none (torch 2.1's workaround forced on
    and off) against a float64 loop: d out[b, c] / d w[b, k] = table[rows[b, k], c]."""
    g = torch.Generator().manual_seed(0)
    table = torch.randn(7, 3, generator=g, dtype=torch.float64)
    rows = torch.randint(0, 7, (4, 5), generator=g)
    w = torch.rand(4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    if workaround:
        monkeypatch.setattr(_compat, "_BAG_WEIGHTS_ONLY_GRAD", False)
    elif not _compat._BAG_WEIGHTS_ONLY_GRAD:
        # where the import-time probe found the plain call broken (torch 2.1), it fails on these inputs too:
        # the reason for the workaround, checked instead of the call
        with pytest.raises(RuntimeError, match="isDifferentiableType"):
            torch.nn.functional.embedding_bag(rows, table, per_sample_weights=w, mode="sum")
        return
    out = _compat.embedding_bag(rows, table, per_sample_weights=w, mode="sum")
    up = torch.randn(4, 3, generator=g, dtype=torch.float64)
    (grad,) = torch.autograd.grad((out * up).sum(), [w])
    want_out = torch.zeros(4, 3, dtype=torch.float64)
    want_grad = torch.zeros(4, 5, dtype=torch.float64)
    for b in range(4):
        for k in range(5):
            want_out[b] += w[b, k].item() * table[rows[b, k]]
            want_grad[b, k] = (table[rows[b, k]] * up[b]).sum()
    torch.testing.assert_close(out.detach(), want_out, atol=1e-12, rtol=0)
    torch.testing.assert_close(grad, want_grad, atol=1e-12, rtol=0)
    assert not table.requires_grad  # the caller's table is untouched


def test_autocast_state_and_disabling():
    assert not _compat.autocast_enabled("cpu")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert _compat.autocast_enabled("cpu")
        with _compat.autocast_off("cpu"):
            assert not _compat.autocast_enabled("cpu")
            assert (torch.ones(2, 2) @ torch.ones(2, 2)).dtype == torch.float32
        assert (torch.ones(2, 2) @ torch.ones(2, 2)).dtype == torch.bfloat16


def test_disabled_grad_scaler_passes_the_loss_through():
    scaler = _compat.grad_scaler("cpu", enabled=False)
    loss = torch.tensor(3.5)
    assert scaler.scale(loss) is loss and not scaler.is_enabled()


def test_is_compiling_is_false_eagerly_and_true_under_compile():
    assert not _compat.is_compiling()
    f = torch.compile(lambda x: x + 1 if _compat.is_compiling() else x - 1, backend="eager")
    assert f(torch.zeros(1)).item() == 1.0


class _Checkpointed:
    """A plain class in a checkpoint (as OpenPCDet's numpy scalars are)."""

    def __init__(self, x):
        self.x = x


def test_add_safe_globals_lets_a_checkpoint_load(tmp_path):
    path = tmp_path / "ckpt.pth"
    torch.save({"obj": _Checkpointed(3)}, path)
    if _compat.add_safe_globals([_Checkpointed]):  # torch >= 2.4: the allow-list, used by weights_only loads
        assert torch.load(path, weights_only=True)["obj"].x == 3
    else:  # older torch: no allow-list; its default load (weights_only=False) takes the class as it is
        assert not hasattr(torch.serialization, "add_safe_globals")
        assert torch.load(path)["obj"].x == 3
