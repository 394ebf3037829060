"""The CPU gather of :func:`~mssf_blocks.functional.bilinear_sample` as one opaque op under ``torch.compile``.

``torch.ops.mssf_blocks.bilinear_gather(image (B, 1, C, H, W), batch_index (N,), uv (N, 2)) -> (N, C)``:
the bilinear samples (``align_corners=False``, zero padding) of the eager CPU path
(:func:`~mssf_blocks.functional.deform.touched.sample_points`: the distinct corner pixels gathered once,
one ``embedding_bag``), registered with ``torch.library`` with a fake implementation and an autograd
formula so that dynamo captures one node of static output shape (the sizes inside it depend on the data).

Why: while a graph is captured, ``bilinear_sample`` otherwise takes the static grid formulation (every
point sampled in each of the ``B`` images, ``F.grid_sample``), which inductor compiles on the CPU into a
scalar loop over ``B x C x N`` reading one NCHW channel plane per step. In the README's
``FusionBlock(MSDFF)`` (query initialisation on the stride-4 level, 256 channels, B = 2, N = 2,000, one
thread) that loop took 30 ms of a 112 ms compiled forward against 95 ms eager (docs/performance.md).
Only ``torch.compile`` takes this op; exporters (``torch.export``, ONNX, tracing) keep the grid
formulation of standard operators.

With gradients, the forward runs the gather under autograd and keeps its graph for the backward by a key
(:mod:`~mssf_blocks.functional.deform.kept`, as the sampling op does), so the backward is eager's.
"""

from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor

from mssf_blocks import torch_versions
from mssf_blocks.functional.deform import kept, touched
from mssf_blocks.functional.deform.op import _autograd_on

__all__ = ["bilinear_gather", "compiled_gather"]


def compiled_gather(device_type: str) -> bool:
    """Whether ``bilinear_sample(method="auto")`` takes this op now: dynamo is capturing (not an exporter), on
    the CPU (elsewhere the grid path is the eager one too), with ``torch.library.custom_op`` available."""
    if device_type != "cpu" or _GATHER is None:
        return False
    if not torch_versions.is_compiling() or torch_versions.is_exporting():
        return False
    onnx = getattr(torch, "onnx", None)
    return not (onnx is not None and onnx.is_in_onnx_export())


def _gather(image: Tensor, batch_index: Tensor, uv: Tensor) -> Tensor:
    if uv.shape[0] == 0 or image.shape[2] == 0:
        return image.new_zeros(uv.shape[0], image.shape[2]) + 0 * uv.sum()
    return touched.sample_points(image, batch_index, uv)


def _owned(t: Tensor, *inputs: Tensor) -> Tensor:
    """``t``, or a copy where it shares memory with an input (a custom op's outputs may alias none)."""
    taken = {x.untyped_storage().data_ptr() for x in inputs}
    return t.clone() if t.untyped_storage().data_ptr() in taken else t


def _grad_inputs(image: Tensor, uv: Tensor, image_grad: bool) -> Tuple[Tensor, Tensor]:
    return image.detach().requires_grad_(image_grad), uv.detach().requires_grad_()


_GATHER = _GATHER_KEEP = None
if torch_versions.has("custom_op"):  # torch >= 2.4; older: bilinear_sample keeps the grid path under compile

    @torch.library.custom_op("mssf_blocks::bilinear_gather", mutates_args=())
    def _op(image: Tensor, batch_index: Tensor, uv: Tensor) -> Tensor:
        return _owned(_gather(image, batch_index, uv).contiguous(), image, uv)

    @torch.library.custom_op("mssf_blocks::bilinear_gather_keep", mutates_args=())
    def _op_keep(image: Tensor, batch_index: Tensor, uv: Tensor, image_grad: bool) -> Tuple[Tensor, Tensor]:
        """The forward under autograd, its graph kept for the backward: ``(out, key)`` (``kept.py``)."""
        with _autograd_on():
            img, loc = _grad_inputs(image, uv, image_grad)
            out = _gather(img, batch_index, loc)
        inputs = [loc, img] if image_grad else [loc]
        return _owned(out.detach().contiguous(), image, uv), kept.keep(out, inputs, ("gather", image_grad))

    @torch.library.custom_op("mssf_blocks::bilinear_gather_backward", mutates_args=())
    def _op_backward(grad: Tensor, image: Tensor, batch_index: Tensor, uv: Tensor, image_grad: bool,
                     graph_key: Tensor) -> Tuple[Tensor, Tensor]:
        graph = kept.take(graph_key, ("gather", image_grad)) if graph_key.numel() else None
        with _autograd_on():
            if graph is None:  # (no graph kept: the forward again, under autograd)
                img, loc = _grad_inputs(image, uv, image_grad)
                graph = _gather(img, batch_index, loc), [loc, img] if image_grad else [loc]
            out, inputs = graph
            grads = torch.autograd.grad(out, inputs, grad, allow_unused=True)
        grads = [torch.zeros_like(t) if g is None else g for g, t in zip(grads, inputs)]
        g_image = grads[1] if image_grad else torch.zeros_like(image)
        return _owned(g_image, grad, image, uv), _owned(grads[0], grad, image, uv)

    @_op.register_fake
    def _(image, batch_index, uv):
        return uv.new_empty(uv.shape[0], image.shape[2], dtype=image.dtype)

    @_op_keep.register_fake
    def _(image, batch_index, uv, image_grad):
        # (the key lives on the CPU: kept.keep makes it there)
        return uv.new_empty(uv.shape[0], image.shape[2], dtype=image.dtype), torch.empty((), dtype=torch.int64)

    @_op_backward.register_fake
    def _(grad, image, batch_index, uv, image_grad, graph_key):
        return torch.empty_like(image), torch.empty_like(uv)

    def _save(ctx, inputs, graph_key):
        image, batch_index, uv = inputs[:3]
        ctx.image_grad, ctx.extra = image.requires_grad, len(inputs) - 3
        ctx.save_for_backward(image, batch_index, uv, graph_key)

    def _backward(ctx, grad, *_):
        image, batch_index, uv, graph_key = ctx.saved_tensors
        g_image, g_uv = _op_backward(grad, image, batch_index, uv, ctx.image_grad, graph_key)
        return (g_image if ctx.image_grad else None, None, g_uv) + (None,) * ctx.extra

    _op.register_autograd(_backward, setup_context=lambda ctx, inputs, output: _save(
        ctx, inputs, torch.empty(0, dtype=torch.int64)))
    _op_keep.register_autograd(_backward, setup_context=lambda ctx, inputs, output: _save(ctx, inputs, output[1]))
    _GATHER, _GATHER_KEEP = _op, _op_keep


def bilinear_gather(image: Tensor, batch_index: Tensor, uv: Tensor) -> Tensor:
    """``(N, C)`` bilinear samples of ``image (B, 1, C, H, W)`` at ``uv (N, 2)`` of images ``batch_index``
    through the op (inputs unchecked: ``bilinear_sample`` checked them); with gradients the keeping op."""
    if torch.is_grad_enabled() and (image.requires_grad or uv.requires_grad):
        return _GATHER_KEEP(image, batch_index, uv, image.requires_grad)[0]
    return _GATHER(image, batch_index, uv)
