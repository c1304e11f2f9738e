"""Model shapes, reference parameter counts, batching, functional evaluation and the context vector."""

import math

import pytest
import torch
from torch.func import functional_call, vmap

from mapless.agent.acting import observation_keys
from mapless.config import ConfigError
from mapless.errors import UnknownNameError
from mapless.knowledge import normalize_adjacency, synthetic_knowledge
from mapless.models import ModelConfig, build_model, context_vector, count_parameters, model_names
from mapless.models.layers import pointwise_conv, pointwise_conv_of_parts, tile
from mapless.models.synthetic import synthetic_observations

#: The paper's comparison (and the mlp sanity model).
COMPARISON = ["random", "a3c", "sp", "savn", "gve", "spatt", "mjolnir_o", "mjolnir_r", "cvmeta", "mlp"]
#: Every registered model: a new one gets the generic checks below without an edit here.
ALL = model_names()


@pytest.fixture(scope="module")
def tiny():
    return synthetic_knowledge(6, 300, seed=0)


def test_every_model_of_the_comparison_is_registered():
    assert model_names()[: len(COMPARISON)] == COMPARISON
    with pytest.raises(UnknownNameError, match="mjolnir_o"):
        build_model("mjolnir-o")


# Reference numbers: docs/reference-implementations.md §3 (instantiated originals) and
# baselines-gve-spatt.md §1.3 (SpAtt, arithmetic). (trainable, state-dict total)
REFERENCE_COUNTS = {
    "a3c": (7_577_491, 7_577_491),
    "savn": (8_115_539, 8_115_539),
    "spatt": (7_566_070, 7_566_070),
    "mjolnir_o": (3_558_001, 3_588_301),
    "mjolnir_r": (9_018_253, 9_561_553),
}
REFERENCE_SHAPES = {
    "a3c": {
        "conv1.weight": (64, 512, 1, 1),
        "pointwise.weight": (64, 138, 1, 1),
        "lstm.weight_ih": (2048, 3136),
        "action_predict_linear.weight": (6, 6272),
        "embed_glove.weight": (64, 300),
    },
    "savn": {
        "ll_tc.ll_temporal_block0.ll_conv1.weight": (10, 6, 2),
        "ll_tc.ll_temporal_block0.ll_conv2.weight": (10, 10, 2),
        "ll_tc.ll_temporal_block1.ll_conv1.weight": (1, 10, 2),
        "ll_tc.ll_temporal_block1.ll_conv2.weight": (1, 1, 2),
        "ll_key.weight": (518, 518),
    },
    "mjolnir_o": {
        "A": (101, 101),
        "all_glove": (101, 300),
        "lstm.weight_ih": (2048, 1027),
        "W0.weight": (401, 401),
        "W2.weight": (5, 401),
        "W3.weight": (1, 10),
        "final_mapping.weight": (512, 101),
        "action_predict_linear.weight": (6, 2054),
    },
    "mjolnir_r": {"lstm.weight_ih": (2048, 3648), "resnet18.1.weight": (1000, 512)},
    "spatt": {
        "embed_state.weight": (64, 512, 1),
        "memory_alpha.weight": (3, 512, 1),
        "lstm.weight_ih": (2048, 3136),
    },
}


@pytest.mark.parametrize("name", sorted(REFERENCE_COUNTS))
def test_reference_sized_models_reproduce_reference_counts_and_keys(name):
    model = build_model(name, feature_channels=512, reference_extras=True)
    assert count_parameters(model) == REFERENCE_COUNTS[name]
    state = model.state_dict()
    for key, shape in REFERENCE_SHAPES[name].items():
        assert tuple(state[key].shape) == shape, key
    # Without the dead modules only the documented ones go (docs/guide/models.md).
    lean = build_model(name, feature_channels=512)
    dead = {
        "a3c": 37_638,
        "savn": 37_638 + 2 * 268_842 + 213,
        "spatt": 213,
        "mjolnir_o": 12_330,
        "mjolnir_r": 43_782,
    }[name]
    assert count_parameters(lean)[0] == REFERENCE_COUNTS[name][0] - dead


def test_scene_priors_and_gve_sizes():
    sp = build_model("sp", feature_channels=512)
    assert tuple(sp.lstm.weight_ih.shape) == (2048, 3648)
    assert tuple(sp.graph.W0.weight.shape) == (1024, 1024)
    gve = build_model("gve", feature_channels=512)
    assert tuple(gve.lstm.weight_ih.shape) == (2048, 3136)
    assert tuple(gve.critic_linear.weight.shape) == (1, 1024)


def test_cvmeta_gcn_width_is_a_knob():
    """``gcn_hidden`` narrows the GCN's layers, not its input (C + 300) or its output (64 per node)."""
    default, narrow = build_model("cvmeta"), build_model("cvmeta", gcn_hidden=48)
    assert tuple(default.W1.weight.shape) == (401, 401)
    assert [tuple(narrow.get_submodule(w).weight.shape) for w in ("W0", "W1", "W2")] == [
        (48, 401),
        (48, 48),
        (64, 48),
    ]
    in_view = (torch.rand(3, 101, generator=torch.Generator().manual_seed(0)) < 0.1).float()
    assert narrow.graph_descriptor(in_view).shape == default.graph_descriptor(in_view).shape == (3, 64, 101)
    with pytest.raises(ConfigError, match="gcn_hidden"):
        build_model("cvmeta", gcn_hidden=0)


@pytest.mark.parametrize("name", ALL)
def test_real_size_forward_shapes(name):
    model = build_model(name).eval()
    knowledge = model.knowledge
    obs = synthetic_observations(2, knowledge)
    out = model(obs, model.initial_state(2), torch.zeros(2, 6))
    assert out.logits.shape == (2, 6) and out.value.shape == (2, 1)
    assert out.hidden[0].shape == (2, 512) and out.hidden[1].shape == (2, 512)
    assert torch.isfinite(out.logits).all() and torch.isfinite(out.value).all()


@pytest.mark.parametrize("name", ALL)
def test_batched_forward_equals_per_episode_forward(name, tiny):
    torch.manual_seed(0)
    model = build_model(name, knowledge=tiny, hidden_size=24).eval()
    gen = torch.Generator().manual_seed(1)
    obs = synthetic_observations(3, tiny, generator=gen)
    hidden = (torch.randn(3, 24, generator=gen), torch.randn(3, 24, generator=gen))
    policy = torch.softmax(torch.randn(3, 6, generator=gen), -1)
    batched = model(obs, hidden, policy)
    for b in range(3):
        single = model(
            {k: v[b : b + 1] for k, v in obs.items()},
            (hidden[0][b : b + 1], hidden[1][b : b + 1]),
            policy[b : b + 1],
        )
        assert torch.allclose(batched.logits[b], single.logits[0], atol=1e-5)
        assert torch.allclose(batched.value[b], single.value[0], atol=1e-5)
        assert torch.allclose(batched.hidden[0][b], single.hidden[0][0], atol=1e-5)


@pytest.mark.parametrize("name", [n for n in ALL if n != "random"])
def test_functional_call_uses_the_given_parameters(name, tiny):
    torch.manual_seed(0)
    model = build_model(name, knowledge=tiny, hidden_size=24).eval()
    obs = synthetic_observations(2, tiny, generator=torch.Generator().manual_seed(2))
    args = (obs, model.initial_state(2), torch.zeros(2, 6))
    params = dict(model.named_parameters())
    same = functional_call(model, params, args)
    assert torch.equal(same.logits, model(*args).logits)
    shifted = {n: p + 0.1 for n, p in params.items()}
    assert not torch.allclose(functional_call(model, shifted, args).logits, same.logits)


def test_random_model_is_uniform_and_stateless(tiny):
    model = build_model("random", knowledge=tiny)
    hidden = (torch.ones(2, 512), torch.zeros(2, 512))
    out = model(synthetic_observations(2, tiny), hidden, torch.zeros(2, 6))
    assert torch.allclose(torch.softmax(out.logits, -1), torch.full((2, 6), 1 / 6))
    assert out.hidden is hidden and count_parameters(model) == (0, 0)


def test_context_vector_of_a_hand_built_pose():
    # Category 0: two instances in view, boxes (30, 60, 90, 120) and (60, 90, 150, 210) px of the 300 px
    # frame -> union box (30, 60, 150, 210): centre (90, 135) / 300, area 120 * 150 / 300². Category 1: one
    # box (0, 0, 300, 30). Category 2: not in view.
    context = torch.tensor(
        [
            [
                [1.0, 90 / 300, 135 / 300, 120 * 150 / 300**2],
                [1.0, 150 / 300, 15 / 300, 300 * 30 / 300**2],
                [0.0, 0.0, 0.0, 0.0],
            ]
        ]
    )
    glove = torch.tensor([[3.0, 0.0, 4.0], [1.0, 1.0, 0.0], [0.0, 2.0, 0.0]])
    target = torch.tensor([[1.0, 0.0, 0.0]])
    cv = context_vector({"context": context, "target_embedding": target}, glove)
    expected = torch.tensor(
        [[[1.0, 0.3, 0.45, 0.2, 3 / 5], [1.0, 0.5, 0.05, 0.1, 1 / math.sqrt(2)], [0.0, 0.0, 0.0, 0.0, 0.0]]]
    )
    assert torch.allclose(cv, expected, atol=1e-7)


def test_cs_column_uses_the_packaged_glove_table():
    model = build_model("mjolnir_o")
    names = model.knowledge.category_names
    glove = model.all_glove
    target = glove[names.index("Television")].unsqueeze(0)
    cs = context_vector({"context": torch.zeros(1, len(names), 4), "target_embedding": target}, glove)[
        0, :, 4
    ]
    sofa = names.index("Sofa")
    by_hand = float(glove[sofa] @ target[0] / (glove[sofa].norm() * target[0].norm()))
    assert cs[names.index("Television")].item() == pytest.approx(1.0, abs=1e-6)
    assert cs[sofa].item() == pytest.approx(by_hand, abs=1e-6)


def test_graphs_per_model():
    cv = build_model("cvmeta")
    assert torch.allclose(cv.A, torch.as_tensor(normalize_adjacency(cv.knowledge.graph("hierarchical"))))
    assert cv.A.requires_grad and not cv.all_glove.requires_grad
    mj = build_model("mjolnir_o")
    assert torch.allclose(mj.A, torch.as_tensor(normalize_adjacency(mj.knowledge.graph("vg"))))
    ablated = build_model("cvmeta", hierarchy_rooms=("kitchen", "bedroom", "bathroom"))
    assert not torch.allclose(ablated.A, cv.A)
    assert build_model(ModelConfig(name="cvmeta", graph="vg")).A.shape == (101, 101)


def test_inner_step_skips_only_parameters_the_learned_loss_cannot_reach(tiny):
    for name in ["savn", "gve", "spatt", "cvmeta"]:
        torch.manual_seed(0)
        model = build_model(name, knowledge=tiny, hidden_size=16, interaction_steps=2, adapt="all").eval()
        savn_rule = [n for n, p in model.named_parameters() if p.requires_grad and "ll" not in n]
        skipped = sorted(set(savn_rule) - set(model.inner_parameter_names()))
        assert all(n.startswith(("critic_linear", "gve.")) for n in skipped), (name, skipped)
        obs = synthetic_observations(1, tiny)
        hidden, policy, rows = model.initial_state(1), torch.zeros(1, 6), []
        for _ in range(2):
            out = model(obs, hidden, policy)
            hidden, policy = out.hidden, torch.softmax(out.logits, -1)
            rows.append(torch.cat([hidden[0], policy], -1))
        params = dict(model.named_parameters())
        grads = torch.autograd.grad(
            model.learned_loss(torch.stack(rows, 1)).sum(), [params[n] for n in skipped], allow_unused=True
        )
        assert all(g is None for g in grads)


def test_gve_graph_enters_the_critic_only(tiny):
    torch.manual_seed(0)
    model = build_model("gve", knowledge=tiny, hidden_size=16).eval()
    obs = synthetic_observations(2, tiny)
    args = (obs, model.initial_state(2), torch.zeros(2, 6))
    base = model(*args)
    params = {n: (p + 0.5 if n.startswith("gve.") else p) for n, p in model.named_parameters()}
    moved = functional_call(model, params, args)
    assert torch.equal(moved.logits, base.logits) and not torch.allclose(moved.value, base.value)


def test_spatt_attention_is_uniform_at_initialisation(tiny):
    model = build_model("spatt", knowledge=tiny, hidden_size=16).eval()
    obs = synthetic_observations(2, tiny)
    _, p = model.attention(obs, model.initial_state(2), torch.zeros(2, 6))
    assert torch.allclose(p, torch.full((2, 49), 1 / 49))


def test_inner_learning_rates():
    assert build_model("savn", feature_channels=8).inner_lr == 1e-4
    assert build_model("spatt", feature_channels=8).inner_lr == 0.01
    assert build_model("cvmeta").inner_lr == 1e-3
    assert build_model("cvmeta", inner_lr=0.5).inner_lr == 0.5
    with pytest.raises(TypeError):
        _ = build_model("a3c", feature_channels=8).inner_lr


def test_cli_lists_models_with_reference_counts(capsys):
    from mapless.cli import main

    assert main(["models", "list", "--reference"]) == 0
    out = capsys.readouterr().out
    lines = {line.split()[0]: line for line in out.splitlines()[1:]}
    assert list(lines) == ALL
    assert "7,577,491" in lines["a3c"] and "8,115,539" in lines["savn"]
    assert "3,558,001" in lines["mjolnir_o"] and "3,588,301" in lines["mjolnir_o"]


def test_policy_adaptation_keeps_the_encoders_fixed(tiny):
    cvmeta = build_model("cvmeta", knowledge=tiny, hidden_size=16, interaction_steps=2)
    assert cvmeta.config.adapt is None and cvmeta.default_adapt == "policy"
    names = cvmeta.inner_parameter_names()
    assert {"lstm.weight_ih", "lstm.weight_hh", "pointwise.weight", "actor_linear.weight"} <= set(names)
    assert not any(n.startswith(("W0", "W1", "W2", "A", "context_embed", "embed_glove")) for n in names)
    everything = build_model("cvmeta", knowledge=tiny, hidden_size=16, interaction_steps=2, adapt="all")
    assert {"W0.weight", "A", "context_embed.weight"} <= set(everything.inner_parameter_names())
    savn = build_model("savn", knowledge=tiny, hidden_size=16, interaction_steps=2, adapt="policy")
    assert "conv1.weight" not in savn.inner_parameter_names()
    assert "pointwise.weight" in savn.inner_parameter_names()
    with pytest.raises(ConfigError, match=r"model\.adapt"):
        ModelConfig(name="cvmeta", adapt="encoders")


class _Pointwise(torch.nn.Module):
    def __init__(self, conv):
        super().__init__()
        self.conv = conv

    def forward(self, x):
        return pointwise_conv(self.conv, x)


def test_pointwise_conv_equals_the_convolution_also_with_per_episode_weights_under_vmap():
    torch.manual_seed(0)
    for conv, x in (
        (torch.nn.Conv2d(6, 4, 1), torch.randn(3, 6, 7, 7)),
        (torch.nn.Conv1d(5, 4, 1), torch.randn(3, 5, 11)),
    ):
        torch.testing.assert_close(pointwise_conv(conv, x), conv(x))
        # Per-episode weights, as the inner loop's fast weights: one episode per vmap lane.
        weights = {n: p.detach() + 0.1 * torch.randn(3, *p.shape) for n, p in conv.named_parameters()}
        expected = vmap(lambda w, xi, m=conv: functional_call(m, w, (xi[None],))[0])(weights, x)
        wrapped, lanes = _Pointwise(conv), {f"conv.{n}": w for n, w in weights.items()}
        got = vmap(lambda w, xi, m=wrapped: functional_call(m, w, (xi[None],))[0])(lanes, x)
        torch.testing.assert_close(got, expected)


def test_pointwise_conv_of_parts_equals_the_conv_of_the_concatenation_to_second_order():
    torch.manual_seed(0)
    conv = torch.nn.Conv1d(4 + 3 + 2 + 5, 6, 1).double()
    maps = [torch.randn(2, 4, 9, dtype=torch.float64), torch.randn(2, 3, 9, dtype=torch.float64)]
    vectors = [torch.randn(2, 2, dtype=torch.float64), torch.randn(2, 5, dtype=torch.float64)]
    inputs = [*maps, *vectors, *conv.parameters()]
    for t in inputs:
        t.requires_grad_()

    def loss(fused):
        # An inner gradient inside the loss: the second-order path of the meta-learning inner loop.
        (inner,) = torch.autograd.grad(fused.tanh().pow(2).sum(), conv.weight, create_graph=True)
        return fused.sin().sum() + inner.pow(2).sum()

    whole = pointwise_conv(conv, torch.cat([*maps, *(tile(v, 9) for v in vectors)], dim=1))
    parts = pointwise_conv_of_parts(conv, maps, vectors)
    torch.testing.assert_close(parts, whole)
    expected = torch.autograd.grad(loss(whole), inputs)
    got = torch.autograd.grad(loss(parts), inputs)
    for g, e in zip(got, expected, strict=True):
        torch.testing.assert_close(g, e)


@pytest.mark.parametrize("name", [n for n in COMPARISON if n not in ("random", "mlp")])
def test_target_context_reaches_every_model_through_the_targets_own_row(name, tiny):
    """``model.target_context`` gives every model the target's own context row: the outputs move when
    only that row changes, through the parameters the option adds (off: models that read no context
    rows do not move at all)."""
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(3)
    obs = synthetic_observations(2, tiny, generator=gen)
    obs["target_index"] = torch.tensor([1, 4])
    moved = {k: v.clone() for k, v in obs.items()}
    moved["context"][torch.arange(2), obs["target_index"]] += torch.tensor([1.0, 0.3, -0.2, 0.5])
    args = lambda o: (o, (torch.zeros(2, 24), torch.zeros(2, 24)), torch.full((2, 6), 1 / 6))  # noqa: E731
    with_row = build_model(name, knowledge=tiny, hidden_size=24, target_context=True).eval()
    with torch.no_grad():  # away from the initialisation, where spatt's attention ignores its queries
        for p in with_row.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=gen))
    out, out_moved = with_row(*args(obs)), with_row(*args(moved))
    assert not torch.allclose(out.value, out_moved.value)
    (out.value.sum() + out.logits.sum()).backward()
    if name == "mjolnir_o":  # no target descriptor: the row is the LSTM input's last 4 columns
        assert with_row.lstm.weight_ih.grad[:, -4:].abs().sum() > 0
    else:
        assert with_row.embed_target_context.weight.grad.abs().sum() > 0
    without = build_model(name, knowledge=tiny, hidden_size=24).eval()
    assert not any("target_context" in n for n, _ in without.named_parameters())
    if name in ("a3c", "savn"):  # they read the feature map only, never a context row
        assert torch.equal(without(*args(obs)).value, without(*args(moved)).value)


def test_cvmeta_reads_the_semantic_map_only_with_the_option(tiny):
    """``model.semantic_map`` adds the 7x7 feature map's 1x1 embedding to cvmeta's LSTM input (an
    encoder parameter, so policy-only adaptation keeps it fixed); without it the map is never read."""
    gen = torch.Generator().manual_seed(5)
    obs = synthetic_observations(2, tiny, generator=gen)
    moved = {**obs, "features": obs["features"] + torch.rand(obs["features"].shape, generator=gen)}
    args = lambda o: (o, (torch.zeros(2, 24), torch.zeros(2, 24)), torch.full((2, 6), 1 / 6))  # noqa: E731
    with_map = build_model(
        "cvmeta", knowledge=tiny, hidden_size=24, fusion_channels=2, semantic_map=True
    ).eval()
    without = build_model("cvmeta", knowledge=tiny, hidden_size=24, fusion_channels=2).eval()
    assert with_map.lstm.weight_ih.shape[1] == without.lstm.weight_ih.shape[1] + 16 * 49
    assert not torch.allclose(with_map(*args(obs)).logits, with_map(*args(moved)).logits)
    assert torch.equal(without(*args(obs)).logits, without(*args(moved)).logits)
    assert with_map.parameter_role_map()["embed_map.weight"] == "encoder"
    assert "embed_map.weight" not in with_map.inner_parameter_names()


def test_models_read_the_context_distance_only_with_the_option(tiny):
    """``model.context_distance`` adds a distance column to cvmeta's context vector and to its target
    row; without it the observation key is never read (so no environment computes it)."""
    gen = torch.Generator().manual_seed(6)
    obs = synthetic_observations(2, tiny, generator=gen)
    obs["target_index"] = torch.tensor([1, 4])
    moved = {**obs, "context_distance": obs["context_distance"] + 1.0}
    args = lambda o: (o, (torch.zeros(2, 24), torch.zeros(2, 24)), torch.full((2, 6), 1 / 6))  # noqa: E731
    small = {"knowledge": tiny, "hidden_size": 24, "fusion_channels": 2, "target_context": True}
    with_distance = build_model("cvmeta", context_distance=True, **small).eval()
    without = build_model("cvmeta", **small).eval()
    assert with_distance.context_embed.weight.shape[1] == without.context_embed.weight.shape[1] + 1 == 6
    assert with_distance.embed_target_context.weight.shape[1] == 5
    assert not torch.allclose(with_distance(*args(obs)).logits, with_distance(*args(moved)).logits)
    assert torch.equal(without(*args(obs)).logits, without(*args(moved)).logits)
    assert "context_distance" in observation_keys(with_distance)
    assert "context_distance" not in observation_keys(without)
    # SAVN's embedding (a3c and its kin) reads it in the target row only.
    a3c = build_model("a3c", context_distance=True, **small).eval()
    assert a3c.embed_target_context.weight.shape[1] == 5 and "context_distance" in observation_keys(a3c)
    far = {**obs, "context_distance": obs["context_distance"].clone()}
    far["context_distance"][torch.arange(2), obs["target_index"]] += 1.0
    assert not torch.allclose(a3c(*args(obs)).logits, a3c(*args(far)).logits)


def test_adapt_none_makes_an_adaptive_model_a_plain_recurrent_policy(tiny):
    """The same network (same parameters, same forward) that neither meta-learns nor adapts."""
    plain = build_model("cvmeta", knowledge=tiny, hidden_size=24, fusion_channels=2, adapt="none")
    meta = build_model("cvmeta", knowledge=tiny, hidden_size=24, fusion_channels=2)
    assert type(plain).is_adaptive() and meta.adaptive and not plain.adaptive
    assert [n for n, _ in plain.named_parameters()] == [n for n, _ in meta.named_parameters()]
    with pytest.raises(ConfigError, match=r"model\.adapt"):
        build_model("cvmeta", adapt="sometimes")
