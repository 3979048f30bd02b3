"""Small networks of one latent z [D] (the colour transform's MLP, the residual's projection of z, the sky's MLP),
evaluated as matrix-vector products."""

import torch
from torch import Tensor, nn


def latent_mlp(mlp: nn.Module, z: Tensor) -> Tensor:
    """`mlp(z)` of one latent z [D] for an nn.Linear or an nn.Sequential of them and activations: each Linear as one
    addmv (bias + W z). nn.Linear on a vector reshapes it to a one-row matrix, runs addmm and reshapes back, three
    operators (and backward nodes) more per layer, paid every training step; the numbers are the same
    (tests/appearance/test_latent_mlp.py). A batch of latents goes through the module itself."""
    if z.dim() != 1:
        return mlp(z)
    x = z
    for layer in mlp if isinstance(mlp, nn.Sequential) else (mlp,):
        if isinstance(layer, nn.Linear):
            x = torch.mv(layer.weight, x) if layer.bias is None else torch.addmv(layer.bias, layer.weight, x)
        else:
            x = layer(x)
    return x
