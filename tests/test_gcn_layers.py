"""The factored GCN layers of mapless.models.base against the plain formulas, values and gradients."""

import pytest
import torch
from torch import nn

from mapless.models.layers import gcn_layer, shared_gcn_term, shared_row_gcn_layer

C, B, FEATURES = 6, 4, 5


def _inputs(bias: bool, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    adjacency = torch.rand(C, C, generator=g, dtype=torch.float64).requires_grad_()
    in_view = (torch.rand(B, C, generator=g) < 0.4).double().requires_grad_()
    node_features = torch.randn(C, FEATURES, generator=g, dtype=torch.float64).requires_grad_()
    layer = nn.Linear(C + FEATURES, 7, bias=bias).double()
    if bias:
        nn.init.normal_(layer.bias)
    return adjacency, in_view, node_features, layer


def _factored_first_layer(adjacency, in_view, node_features, layer):
    return shared_row_gcn_layer(adjacency, in_view, shared_gcn_term(adjacency, node_features, layer), layer)


def _plain_first_layer(adjacency, in_view, node_features, layer):
    """``layer(Â · [v || F])`` per episode with the ``[B, C, C + D]`` input formed, node-major out."""
    rows = torch.cat([in_view.unsqueeze(1).expand(B, C, C), node_features.expand(B, C, FEATURES)], -1)
    return layer(adjacency @ rows).transpose(0, 1)


@pytest.mark.parametrize("bias", [False, True])
def test_shared_row_layer_equals_the_formed_input(bias):
    adjacency, in_view, node_features, layer = _inputs(bias)
    wrt = [adjacency, in_view, node_features, *layer.parameters()]
    expected = _plain_first_layer(adjacency, in_view, node_features, layer)
    got = _factored_first_layer(adjacency, in_view, node_features, layer)
    torch.testing.assert_close(got, expected)
    upstream = torch.randn_like(expected)
    # In-place activation on the result, as the models apply it.
    grads = torch.autograd.grad((torch.relu_(got) * upstream).sum(), wrt)
    expected_grads = torch.autograd.grad((torch.relu(expected) * upstream).sum(), wrt)
    for a, e in zip(grads, expected_grads, strict=True):
        torch.testing.assert_close(a, e)


def test_shared_row_layer_second_order():
    adjacency, in_view, node_features, layer = _inputs(bias=True, seed=3)

    def hessian_vector(fn):
        out = torch.tanh(fn(adjacency, in_view, node_features, layer)).sum()
        (g,) = torch.autograd.grad(out, layer.weight, create_graph=True)
        return torch.autograd.grad((g**2).sum(), [adjacency, in_view])

    for a, e in zip(hessian_vector(_factored_first_layer), hessian_vector(_plain_first_layer), strict=True):
        torch.testing.assert_close(a, e)


def test_shared_row_layer_stays_in_bfloat16_under_autocast():
    *tensors, layer = _inputs(bias=False, seed=5)
    adjacency, in_view, node_features = (t.detach().float() for t in tensors)
    layer = layer.float()
    full = _factored_first_layer(adjacency, in_view, node_features, layer)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = _factored_first_layer(adjacency, in_view, node_features, layer)
    assert low.dtype == torch.bfloat16 and full.dtype == torch.float32
    torch.testing.assert_close(low.float(), full, atol=0.05, rtol=0.02)


@pytest.mark.parametrize("out_features", [3, 9])  # narrowing (Â applied after W) and widening
def test_gcn_layer_equals_propagate_then_linear(out_features):
    g = torch.Generator().manual_seed(7)
    adjacency = torch.rand(C, C, generator=g, dtype=torch.float64)
    x = torch.randn(C, B, FEATURES, generator=g, dtype=torch.float64, requires_grad=True)
    layer = nn.Linear(FEATURES, out_features, bias=False).double()
    expected = layer(torch.einsum("ij,jbf->ibf", adjacency, x))
    got = gcn_layer(adjacency, x, layer)
    torch.testing.assert_close(got, expected)
    (gx,) = torch.autograd.grad(got.sum(), x)
    (ex,) = torch.autograd.grad(expected.sum(), x)
    torch.testing.assert_close(gx, ex)
