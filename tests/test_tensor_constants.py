"""tensor_constants.constant: a number as a cached 0-dim tensor, the same results as the Python number."""

import torch

from willags_ns.tensor_constants import constant


def test_same_results_as_the_python_number_and_made_once():
    x = torch.randn(1000)
    for v in (0.5, 0.005, 1e-4, 9e-4, 0.8, 100.0):
        assert torch.equal(x * constant(v, x), x * v)
        assert torch.equal(x + constant(v, x), x + v)
        assert torch.equal(constant(v, x) - x, v - x)
    assert constant(0.5, x) is constant(0.5, x)
    assert constant(0.5, x.double()).dtype == torch.float64


def test_usable_in_autograd_when_first_made_under_inference_mode():
    with torch.inference_mode():
        c = constant(0.25, torch.zeros(1, dtype=torch.float16))
    assert not c.is_inference()
    x = torch.randn(3, dtype=torch.float16, requires_grad=True)
    (x * c).sum().backward()
    assert x.grad is not None


def test_as_dtype_returns_the_tensor_itself_when_nothing_changes():
    from willags_ns.tensor_constants import as_dtype

    x = torch.randn(4)
    assert as_dtype(x, torch.float32) is x
    y = as_dtype(x, torch.float64)
    assert y.dtype == torch.float64 and torch.equal(y, x.double())
