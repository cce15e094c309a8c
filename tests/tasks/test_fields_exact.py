"""The fitting tasks' fields (sp_plugins.tasks.fields), exactly: the encoding defaults and the bounds
``validate`` refuses at their edges, FINER's activation and initialisation, each encoding as built
(widths, octaves, grid levels), the MLP's shape and activations, the geometric initialisation, and the
coordinates each part of a field reads (``[-1, 1]`` for the MLP and Fourier features, ``[0, 1]`` for
grids). The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from sp_plugins.tasks.fields import EncodingConfig, FinerLayer, NeuralField, make_encoding


def test_the_encoding_defaults():
    """The encoding's defaults: a hash grid of 16 levels of 2 features, 2^16 entries, resolutions 16 to 1024; 8
    Fourier frequencies; 128 x 128 planes of 16 features; FINER's omega 30 and bias scale 1."""
    c = EncodingConfig()
    assert (c.kind, c.levels, c.features_per_level, c.log2_table_size, c.base_resolution, c.max_resolution) == ("hashgrid", 16, 2, 16, 16, 1024)
    assert (c.frequencies, c.plane_resolution, c.plane_features, c.finer_omega, c.finer_bias_scale) == (8, 128, 16, 30.0, 1.0)


GRID = "hashgrid: need levels >= 1 and 2 <= base_resolution <= max_resolution (got {}, {}, {})"
SIZES = "fourier frequencies, triplane resolution and features must be positive"


@pytest.mark.parametrize("change, message", [
    (dict(levels=0), GRID.format(0, 16, 1024)),
    (dict(base_resolution=1, max_resolution=1), GRID.format(16, 1, 1)),
    (dict(base_resolution=16, max_resolution=15), GRID.format(16, 16, 15)),
    (dict(frequencies=0), SIZES),
    (dict(plane_resolution=1), SIZES),
    (dict(plane_features=0), SIZES),
    (dict(kind="sirens"), "encoding kind='sirens' is not known; allowed values: hashgrid, fourier, triplane, finer"),
])
def test_validate_refuses_each_bound_at_its_edge_alone(change, message):
    """Each refused value alone is refused with its line, and the value at the edge is accepted (levels 1,
    base 2, max = base, frequencies 1, plane resolution 2, plane features 1)."""
    with pytest.raises(ValueError) as e:
        EncodingConfig(**change).validate()
    assert str(e.value) == message
    EncodingConfig(levels=1, base_resolution=2, max_resolution=2, frequencies=1, plane_resolution=2, plane_features=1).validate()
    for kind in ("hashgrid", "fourier", "triplane", "finer"):
        EncodingConfig(kind=kind).validate()


@pytest.mark.parametrize("first", [True, False])
def test_a_finer_layer_is_sin_of_omega_times_abs_z_plus_1_times_z_with_siren_init(first):
    """``sin(omega (|z| + 1) z)``, ``z = W x + b``; the first layer's weights from U(-1/d_in, 1/d_in) and
    its bias from U(-k, k), a later layer's weights from U(-sqrt(6 / d_in) / omega, ...) and nn.Linear's
    bias: the same draws, in the same order, as the formulas here."""
    d_in, d_out, omega, k = 5, 7, 3.0, 0.75
    torch.manual_seed(11)
    layer = FinerLayer(d_in, d_out, omega, first, k)
    torch.manual_seed(11)
    ref = nn.Linear(d_in, d_out).double()
    with torch.no_grad():
        bound = 1.0 / d_in if first else math.sqrt(6.0 / d_in) / omega
        w = torch.empty(d_out, d_in).uniform_(-bound, bound)
        b = torch.empty(d_out).uniform_(-k, k) if first else ref.bias.float()
    torch.testing.assert_close(layer.linear.weight, w, rtol=0, atol=0)
    torch.testing.assert_close(layer.linear.bias, b, rtol=0, atol=0)
    assert layer.linear.weight.abs().max() <= bound and (not first or layer.linear.bias.abs().max() <= k)
    x = torch.randn(4, d_in)
    z = x.double() @ w.double().T + b.double()
    torch.testing.assert_close(layer(x).double(), torch.sin(omega * (z.abs() + 1.0) * z), rtol=1e-5, atol=1e-5)


def test_each_encoding_as_built():
    """Fourier: octaves pi * 2^0 .. pi * 2^(n-1), sines and cosines per axis; hash grid: the config's
    levels, features, table, base and finest resolution on ``dim`` inputs; triplane: the planes summed
    (width = features), 3-D only; FINER: none, width 0."""
    fourier, width = make_encoding(EncodingConfig(kind="fourier", frequencies=3), 2)
    assert width == 2 * 2 * 3 and fourier.n_input_dims == 2
    assert fourier.angular_frequencies == (math.pi, 2 * math.pi, 4 * math.pi)
    config = EncodingConfig(levels=3, features_per_level=4, log2_table_size=10, base_resolution=4, max_resolution=16)
    grid, width = make_encoding(config, 2)
    assert width == 12 and (grid.num_levels, grid.features_per_level, grid.log2_hashmap_size, grid.base_resolution) == (3, 4, 10, 4)
    assert grid.n_input_dims == 2 and grid.levels[-1].resolution == 16 and grid.requested_backend == "auto"
    planes, width = make_encoding(EncodingConfig(kind="triplane", plane_resolution=5, plane_features=6), 3)
    assert width == 6 and (planes.resolution, planes.channels, planes.reduce) == (5, 6, "sum")
    with pytest.raises(ValueError, match="^encoding kind='triplane' is 3D only; use hashgrid or fourier for images$"):
        make_encoding(EncodingConfig(kind="triplane"), 2)
    assert make_encoding(EncodingConfig(kind="finer"), 3) == (None, 0)
    with pytest.raises(ValueError, match="^fourier frequencies"):
        make_encoding(EncodingConfig(kind="fourier", frequencies=0), 3)  # validated first


def linears(field):
    return [m for m in field.mlp if isinstance(m, (nn.Linear, FinerLayer))]


def test_the_mlp_is_linear_layers_with_softplus_100_or_relu_between_and_none_after():
    """Widths ``[d_in, *hidden, out]`` with ``d_in`` = encoding width + dim when the input is included; a
    Softplus of beta 100 (or a ReLU) after every layer but the last."""
    enc = EncodingConfig(kind="fourier", frequencies=2)
    field = NeuralField(enc, dim=3, out_dim=2, hidden=(5, 6), include_input=True)
    assert [(m.in_features, m.out_features) for m in linears(field)] == [(3 * 4 + 3, 5), (5, 6), (6, 2)]
    kinds = [type(m).__name__ for m in field.mlp]
    assert kinds == ["Linear", "Softplus", "Linear", "Softplus", "Linear"] and field.mlp[1].beta == 100.0
    plain = NeuralField(enc, dim=2, hidden=(4,), include_input=False, activation="relu")
    assert [type(m).__name__ for m in plain.mlp] == ["Linear", "ReLU", "Linear"] and plain.mlp[0].in_features == 2 * 4
    x = torch.rand(4, 5, 3)
    assert field(x).shape == (4, 5, 2) and field(x[0, 0]).shape == (2,)
    with pytest.raises(ValueError, match=r"^activation='tanh': use 'softplus' or 'relu'$"):
        NeuralField(enc, activation="tanh")


def test_a_finer_field_is_finer_layers_then_a_linear_with_a_small_siren_init():
    """FINER always reads the raw coordinates: ``dim`` inputs, a FinerLayer per hidden width (only the
    first marked first: its bias from U(-k, k)), then a Linear whose weights lie within sqrt(6 / w) /
    omega."""
    enc = EncodingConfig(kind="finer", finer_omega=2.0, finer_bias_scale=5.0)
    torch.manual_seed(3)
    field = NeuralField(enc, dim=3, hidden=(64, 64), include_input=False)
    first, second, last = field.mlp
    assert isinstance(first, FinerLayer) and isinstance(second, FinerLayer) and type(last) is nn.Linear
    assert (first.linear.in_features, second.linear.in_features, last.in_features, last.out_features) == (3, 64, 64, 1)
    assert first.linear.bias.abs().max() > 2.0  # U(-5, 5): the first layer's
    assert second.linear.bias.abs().max() <= 1 / 8 and second.linear.weight.abs().max() <= math.sqrt(6 / 64) / 2.0
    torch.manual_seed(3)  # the same draws: the two FINER layers, then the last Linear re-drawn in +-bound
    FinerLayer(3, 64, 2.0, True, 5.0), FinerLayer(64, 64, 2.0, False, 5.0)
    ref = nn.Linear(64, 1)
    bound = math.sqrt(6.0 / 64) / 2.0
    nn.init.uniform_(ref.weight, -bound, bound)
    assert torch.equal(last.weight, ref.weight) and torch.equal(last.bias, ref.bias)
    assert field.include_input is True


def test_a_finer_fields_last_bound_reads_the_last_hidden_width_and_a_parsed_kind():
    """Three hidden widths (16, 8, 4): the last Linear is U(+-sqrt(6 / 4) / omega), exactly the reference's draw
    (4, the last hidden width: ``widths[2]`` is 8 here, the same as ``widths[-2]`` only with two hidden layers);
    the kind named by an equal string built at run time (as a parsed ``--encoding.kind finer`` is) builds the same
    FINER net."""
    enc = EncodingConfig(kind="".join(["fin", "er"]), finer_omega=2.0)
    torch.manual_seed(5)
    field = NeuralField(enc, dim=2, hidden=(16, 8, 4))
    *layers, last = field.mlp
    assert [type(m) for m in layers] == [FinerLayer] * 3 and type(last) is nn.Linear and last.in_features == 4
    torch.manual_seed(5)  # the same draws: the three FINER layers, then the last Linear re-drawn in +-bound
    FinerLayer(2, 16, 2.0, True, 1.0), FinerLayer(16, 8, 2.0, False, 1.0), FinerLayer(8, 4, 2.0, False, 1.0)
    ref = nn.Linear(4, 1)
    bound = math.sqrt(6.0 / 4) / 2.0
    nn.init.uniform_(ref.weight, -bound, bound)
    assert torch.equal(last.weight, ref.weight) and torch.equal(last.bias, ref.bias)


def test_the_mlp_widths_add_the_input_width_and_each_hidden_layer_but_the_last_has_its_activation():
    """One Fourier octave on 3-D (width 6, whose bits 3 shares: ``6 | 3`` is 7 and ``6 ^ 3`` is 5, only ``+`` gives 9;
    the 2-octave field above has width 12, where ``|`` and ``^`` give 15 too) and three hidden widths: an activation
    after each of the first three linears (``len(widths) // 2`` is ``len(widths) - 2`` only for four widths); a FINER
    net's layers chain widths (16, 8, 4) in order."""
    field = NeuralField(EncodingConfig(kind="fourier", frequencies=1), dim=3, hidden=(5, 6, 7))
    assert [(m.in_features, m.out_features) for m in linears(field)] == [(9, 5), (5, 6), (6, 7), (7, 1)]
    assert [type(m).__name__ for m in field.mlp] == ["Linear", "Softplus"] * 3 + ["Linear"]
    assert field(torch.rand(4, 3)).shape == (4, 1)
    finer = NeuralField(EncodingConfig(kind="finer"), dim=2, hidden=(16, 8, 4))
    assert [(m.linear.in_features, m.linear.out_features) for m in finer.mlp[:-1]] == [(2, 16), (16, 8), (8, 4)]


def test_a_fields_defaults_are_two_hidden_64s_and_a_sphere_of_radius_half():
    """``NeuralField(encoding)``: a 3-D SDF field (out 1) with hidden widths 64, 64, Softplus, the input included,
    on [-1, 1]; with ``geometric_init`` the sphere's radius is 0.5 (the last bias -0.5)."""
    enc = EncodingConfig(kind="fourier", frequencies=1)
    field = NeuralField(enc)
    assert [(m.in_features, m.out_features) for m in linears(field)] == [(9, 64), (64, 64), (64, 1)]
    assert type(field.mlp[1]) is nn.Softplus and field.include_input and (field.dim, field.lo, field.hi) == (3, -1.0, 1.0)
    sphere = NeuralField(enc, geometric_init=True)
    assert torch.equal(linears(sphere)[-1].bias, torch.tensor([-0.5]))


def test_a_triplane_is_3d_only_and_a_parsed_kind_names_the_same_encoding():
    """The kind named by an equal string built at run time (as a parsed flag is): ``triplane`` builds the
    triplane on 3-D and is refused on 2-D and 4-D; ``finer`` with ``geometric_init`` is refused like the literal,
    and so is an SDF field of 0 outputs."""
    from sp_plugins.encodings import TriplaneEncoding

    triplane = EncodingConfig(kind="".join(["tri", "plane"]), plane_resolution=4, plane_features=2)
    enc, width = make_encoding(triplane, 3)
    assert type(enc) is TriplaneEncoding and width == 2
    for dim in (2, 4):
        with pytest.raises(ValueError, match=r"^encoding kind='triplane' is 3D only; use hashgrid or fourier for images$"):
            make_encoding(triplane, dim)
    fourier = EncodingConfig(kind="fourier", frequencies=1)
    for bad in (dict(encoding=EncodingConfig(kind="".join(["fin", "er"]))), dict(encoding=fourier, out_dim=0)):
        with pytest.raises(ValueError, match="^geometric_init applies to SDF fields"):
            NeuralField(geometric_init=True, **bad)


@pytest.mark.parametrize("kind", ["hashgrid", "fourier", "triplane", "finer"])
@pytest.mark.parametrize("activation", ["softplus", "relu"])
def test_a_kind_and_activation_named_by_parsed_strings_build_what_the_literals_build(kind, activation):
    """``sp-fit``'s flags arrive as strings equal to the literals, not the same objects: a field built from
    such strings (``"".join``) has the literal-built field's layers, the same initial weights for one seed, and
    reads the same coordinates (the same outputs), without the input where the kind allows."""
    small = dict(levels=2, log2_table_size=8, base_resolution=4, max_resolution=8, frequencies=2, plane_resolution=4,
                 plane_features=2)

    def build(k, a):
        torch.manual_seed(11)
        return NeuralField(EncodingConfig(kind=k, **small), dim=3, hidden=(8,), activation=a, include_input=False)

    literal, parsed = build(kind, activation), build("".join(list(kind)), "".join(list(activation)))
    assert [type(m) for m in parsed.modules()] == [type(m) for m in literal.modules()]
    assert parsed.include_input == literal.include_input == (kind == "finer")
    x = torch.rand(16, 3) * 2 - 1
    torch.testing.assert_close(parsed(x), literal(x), rtol=0, atol=0)


def test_an_unknown_kind_is_named_as_unknown_also_with_geometric_init():
    """The refusal of geometric init for FINER compares the kind before it is validated: an unknown kind (one
    that sorts before "finer") still gets the unknown-kind line."""
    with pytest.raises(ValueError, match=r"^encoding kind='bogus' is not known; allowed values: hashgrid, fourier, triplane, finer$"):
        NeuralField(EncodingConfig(kind="bogus"), geometric_init=True)


def test_geometric_init_is_sal_s_sphere():
    """The last layer's weights N(sqrt(pi) / sqrt(d_in), 1e-4) and bias -radius; every other weight
    N(0, sqrt(2) / sqrt(d_out)) with bias 0; the first layer reads only the coordinates (the encoding's
    columns zero). Refused for FINER, for out_dim != 1, and without the input."""
    torch.manual_seed(0)
    enc = EncodingConfig(levels=2, log2_table_size=8, base_resolution=4, max_resolution=8)
    field = NeuralField(enc, dim=3, hidden=(512, 512), geometric_init=True, init_radius=0.3)
    a, b, last = linears(field)
    assert a.in_features == 3 + 4
    assert torch.equal(a.weight[:, 3:], torch.zeros(512, 4)) and (a.weight[:, :3] != 0).all()
    assert torch.equal(a.bias, torch.zeros(512)) and torch.equal(b.bias, torch.zeros(512)) and torch.equal(last.bias, torch.tensor([-0.3]))
    target = math.sqrt(2.0) / math.sqrt(512)
    for w in (a.weight[:, :3], b.weight):
        assert abs(w.mean().item()) < 0.05 * target and abs(w.std().item() / target - 1) < 0.04
    assert (last.weight - math.sqrt(math.pi) / math.sqrt(512)).abs().max() < 1e-3
    for bad in (dict(encoding=EncodingConfig(kind="finer")), dict(encoding=enc, out_dim=3)):
        with pytest.raises(ValueError, match="^geometric_init applies to SDF fields"):
            NeuralField(geometric_init=True, **bad)
    with pytest.raises(ValueError, match="^geometric_init needs include_input=True"):
        NeuralField(enc, geometric_init=True, include_input=False)
    NeuralField(EncodingConfig(kind="fourier", frequencies=2), out_dim=3, geometric_init=False)


class Seen(nn.Module):
    """Records what it is given, returns it (as a stand-in MLP: the field's own encoding stays)."""

    def __init__(self):
        super().__init__()
        self.inputs = []

    def forward(self, x):
        self.inputs.append(x.detach().clone())
        return x[..., :1] * 0 + x.sum(-1, keepdim=True)


def test_the_mlp_reads_the_box_mapped_to_minus_1_1_and_grids_read_0_1():
    """On the box [2, 6]^2: the MLP's coordinate columns are ``(x - 4) * (2 / 4)``; a hash grid is
    queried at ``(x - 2) / 4``, Fourier features at the [-1, 1] coordinates; any leading batch shape
    comes back with the output axis."""
    x = torch.tensor([[[2.0, 6.0], [4.0, 3.0]], [[5.0, 2.5], [6.0, 6.0]], [[3.0, 4.0], [2.0, 2.0]]])
    unit = (x.reshape(-1, 2) - 2.0) / 4.0
    grid_cfg = EncodingConfig(levels=2, log2_table_size=8, base_resolution=4, max_resolution=8)
    field = NeuralField(grid_cfg, dim=2, hidden=(4,), bounds=(2.0, 6.0))
    grid_in = []
    field.encoding.register_forward_hook(lambda m, args, out: grid_in.append(args[0].detach().clone()))
    field.mlp = Seen()
    out = field(x)
    assert out.shape == (3, 2, 1)
    (grid_seen,) = grid_in
    torch.testing.assert_close(grid_seen, unit, rtol=0, atol=1e-7)
    (mlp_seen,) = field.mlp.inputs
    torch.testing.assert_close(mlp_seen[:, :2], unit * 2.0 - 1.0, rtol=0, atol=1e-7)
    assert mlp_seen.shape == (6, 2 + 4)

    fourier = NeuralField(EncodingConfig(kind="fourier", frequencies=1), dim=2, hidden=(4,), include_input=False, bounds=(2.0, 6.0))
    fourier.mlp = Seen()
    fourier(x)
    (feats,) = fourier.mlp.inputs
    s = unit * 2.0 - 1.0
    expected = torch.cat([torch.sin(math.pi * s), torch.cos(math.pi * s)], dim=-1)
    torch.testing.assert_close(feats.sort(dim=-1).values, expected.sort(dim=-1).values, rtol=0, atol=1e-6)

    finer = NeuralField(EncodingConfig(kind="finer"), dim=2, hidden=(4,), bounds=(2.0, 6.0))
    finer.mlp = Seen()
    finer(x)
    torch.testing.assert_close(finer.mlp.inputs[0], s, rtol=0, atol=1e-7)
