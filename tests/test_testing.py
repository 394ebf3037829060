"""The tolerance table and helpers that every numerical test relies on."""

import pytest
import torch

from mssf_blocks.testing import TOLERANCES, assert_close, gradcheck64, tolerance


def test_tolerance_table_values():
    assert tolerance(torch.float64) == (1e-10, 1e-10)
    assert tolerance(torch.float32) == (1e-5, 1e-5)
    assert tolerance(torch.bfloat16) == (1e-2, 1e-2)
    with pytest.raises(KeyError):
        tolerance(torch.int32)
    assert set(TOLERANCES) >= {torch.float64, torch.float32, torch.bfloat16}


def test_assert_close_uses_dtype_tolerance():
    x = torch.ones(3, dtype=torch.float64)
    assert_close(x + 1e-12, x)
    with pytest.raises(AssertionError):
        assert_close(x + 1e-8, x)  # fine for float32, too large for float64
    assert_close((x + 1e-8).float(), x.float())


def test_gradcheck64_catches_a_wrong_gradient():
    class Wrong(torch.autograd.Function):
        @staticmethod
        def forward(ctx, a):
            return a * 2

        @staticmethod
        def backward(ctx, g):
            return g * 3  # deliberately wrong

    assert gradcheck64(lambda a: a * 2, [torch.randn(3)])
    with pytest.raises(Exception):
        gradcheck64(Wrong.apply, [torch.randn(3)])


def test_errors_name_argument_expected_and_received():
    from mssf_blocks.checks.tensors import check_shape
    from mssf_blocks.errors import MSSFError

    dims = {}
    check_shape(torch.zeros(5, 3), "features", ("N", "C"), dims)
    with pytest.raises(MSSFError, match=r"coords: expected shape \(N=5, 4\), got shape \(6, 4\)"):
        check_shape(torch.zeros(6, 4, dtype=torch.int32), "coords", ("N", 4), dims)
    with pytest.raises(MSSFError, match=r"uv: expected a 3-d tensor"):
        check_shape(torch.zeros(5, 2), "uv", ("N", "V", 2), dims)


def test_assert_close_exact_for_int_and_bool():
    a = torch.tensor([1, 2, 3], dtype=torch.int32)
    assert_close(a, a.clone())
    assert_close(a, a.long())  # same values, another integer dtype
    with pytest.raises(AssertionError, match="exact"):
        assert_close(a, torch.tensor([1, 2, 4], dtype=torch.int32))
    m = torch.tensor([True, False])
    assert_close(m, m.clone())
    with pytest.raises(AssertionError, match="torch.bool"):
        assert_close(m, ~m)


def test_assert_close_tolerance_from_less_precise_dtype():
    x64 = torch.ones(3, dtype=torch.float64)
    x32 = (x64 + 3e-6).float()  # within float32's tolerance, far outside float64's
    # float32 on either side: float32's tolerance (before: float64's when actual was float64)
    assert_close(x32, x64)
    assert_close(x64, x32)
    with pytest.raises(AssertionError) as err:
        assert_close(x64, (x64 + 1e-3).float())
    assert "torch.float64" in str(err.value) and "torch.float32" in str(err.value)
    # an explicit dtype still wins
    with pytest.raises(AssertionError):
        assert_close(x64, x32, dtype=torch.float64)
