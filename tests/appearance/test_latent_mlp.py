"""latent_mlp: an MLP of one latent as matrix-vector products, the same numbers as the module."""

import pytest
import torch
from torch import nn

from willags_ns.appearance.latent_mlp import latent_mlp


@pytest.mark.parametrize("shape", [(64, 64, 12), (64, 16, 48), (3, 5, 7)])
def test_same_output_and_gradients_as_the_module(shape):
    torch.manual_seed(0)
    d_in, hidden, d_out = shape
    mlp = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, d_out))
    nn.init.normal_(mlp[-1].weight)
    z = torch.randn(d_in, requires_grad=True)
    weights = torch.randn(d_out)
    results = []
    for fn in (mlp, lambda v: latent_mlp(mlp, v)):
        params = [z, *mlp.parameters()]
        out = fn(z)
        grads = torch.autograd.grad((out * weights).sum(), params)
        results.append([out.detach(), *grads])
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)


def test_a_single_linear_and_a_batch():
    torch.manual_seed(1)
    lin = nn.Linear(8, 4)
    z = torch.randn(8)
    assert torch.equal(latent_mlp(lin, z), lin(z))
    no_bias = nn.Linear(8, 4, bias=False)
    assert torch.equal(latent_mlp(no_bias, z), no_bias(z))
    batch = torch.randn(5, 8)  # not one latent: the module itself
    assert torch.equal(latent_mlp(lin, batch), lin(batch))
