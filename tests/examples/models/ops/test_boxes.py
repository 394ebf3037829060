"""Box coders against hand-worked codes and float64 round trips."""

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.models.ops.boxes import (
    decode_center,
    decode_residual,
    encode_center,
    encode_residual,
    limit_period,
)


def _random_boxes(n, gen):
    centre = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 10
    size = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 4 + 0.2
    yaw = (torch.rand(n, 1, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi
    return torch.cat([centre, size, yaw], dim=1)


def _yaw_error(a, b):
    return torch.abs(torch.atan2(torch.sin(a - b), torch.cos(a - b)))


def test_residual_code_hand_worked():
    anchor = torch.tensor([[0.0, 0.0, 0.0, 3.0, 4.0, 1.0, 0.0]], dtype=torch.float64)  # BEV diagonal 5
    box = torch.tensor([[5.0, 10.0, 2.0, 6.0, 8.0, 3.0, 0.5]], dtype=torch.float64)
    expected = torch.tensor([[1.0, 2.0, 2.0, math.log(2), math.log(2), math.log(3), 0.5]], dtype=torch.float64)
    torch.testing.assert_close(encode_residual(box, anchor), expected, rtol=0, atol=1e-12)
    sincos = encode_residual(box, anchor, encode_angle_by_sincos=True)
    torch.testing.assert_close(sincos[0, 6:], torch.tensor([math.cos(0.5) - 1.0, math.sin(0.5)], dtype=torch.float64))


@pytest.mark.parametrize("sincos", [False, True])
def test_residual_round_trip_float64(sincos):
    gen = torch.Generator().manual_seed(0)
    boxes, anchors = _random_boxes(500, gen), _random_boxes(500, gen)
    decoded = decode_residual(encode_residual(boxes, anchors, sincos), anchors, sincos)
    assert (decoded[:, :6] - boxes[:, :6]).abs().max() < 1e-9
    assert _yaw_error(decoded[:, 6], boxes[:, 6]).max() < 1e-9
    if not sincos:  # the raw residual is exact, not only modulo 2 pi
        assert (decoded[:, 6] - boxes[:, 6]).abs().max() < 1e-9


def test_residual_broadcasts_one_anchor_set_over_batch():
    gen = torch.Generator().manual_seed(1)
    anchors = _random_boxes(6, gen)
    codes = torch.randn(2, 6, 7, generator=gen, dtype=torch.float64) * 0.1
    boxes = decode_residual(codes, anchors)
    assert boxes.shape == (2, 6, 7)
    torch.testing.assert_close(encode_residual(boxes, anchors), codes, rtol=0, atol=1e-12)


def test_center_code_hand_worked_and_round_trip():
    box = torch.tensor([[1.3, -3.1, 0.7, 2.0, 1.0, 1.5, 0.4]], dtype=torch.float64)
    # u = (1.3 - 0) / 0.5 = 2.6, v = (-3.1 + 4) / 0.5 = 1.8 -> cell (2, 1), offsets (0.6, 0.8)
    cells = torch.tensor([[2, 1]])
    code = encode_center(box, cells, (0.5, 0.5), (0.0, -4.0))
    expected = torch.tensor(
        [[0.6, 0.8, 0.7, math.log(2.0), 0.0, math.log(1.5), math.sin(0.4), math.cos(0.4)]], dtype=torch.float64
    )
    torch.testing.assert_close(code, expected, rtol=0, atol=1e-12)
    gen = torch.Generator().manual_seed(2)
    boxes = _random_boxes(200, gen)
    cells = torch.randint(-5, 5, (200, 2), generator=gen)  # any reference cell, not only the containing one
    decoded = decode_center(encode_center(boxes, cells, (0.4, 0.3), (-1.0, 2.0)), cells, (0.4, 0.3), (-1.0, 2.0))
    assert (decoded[:, :6] - boxes[:, :6]).abs().max() < 1e-9
    assert _yaw_error(decoded[:, 6], boxes[:, 6]).max() < 1e-9


def test_limit_period_ranges():
    a = torch.tensor([-4.0, -math.pi, 0.0, 3.0, 7.0], dtype=torch.float64)
    wrapped = limit_period(a, 0.5, 2 * math.pi)
    expected = torch.tensor([-4.0 + 2 * math.pi, -math.pi, 0.0, 3.0, 7.0 - 2 * math.pi], dtype=torch.float64)
    torch.testing.assert_close(wrapped, expected)
    half = limit_period(a, 0.0, math.pi)
    assert bool(((half >= 0) & (half < math.pi)).all())


def test_bad_shapes_raise():
    with pytest.raises(MSSFError, match="anchors"):
        encode_residual(torch.zeros(3, 7), torch.zeros(3, 6))
    with pytest.raises(MSSFError, match="codes"):
        decode_residual(torch.zeros(3, 7), torch.zeros(3, 7), encode_angle_by_sincos=True)
    with pytest.raises(MSSFError, match="cell_index"):
        encode_center(torch.ones(3, 7), torch.zeros(2, 2, dtype=torch.long), (1.0, 1.0), (0.0, 0.0))
