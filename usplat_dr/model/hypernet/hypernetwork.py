"""The hypernetworks H_a and H_s: 3-layer MLPs from a 512-d embedding to the weights of the
predictor's target convolutions, and the layouts of what they output.

H_a (view-agnostic) outputs every target layer's full weight and bias, W. H_s (view-specific)
outputs Delta W per target view, either full (``rank=None``) or as a rank-r factorisation
Delta W = U V of each layer's weight seen as a [C_out, C_in * k * k] matrix, plus a bias delta.
The factorised form is our choice (the paper does not say how its MLP reaches the
weight shape): a 3-layer MLP whose last layer emits a full 373k-weight head per view would put
~6M parameters per hidden unit there, and applying a full per-view weight costs a full head
convolution per view, while conv(x, W + U V) = conv(x, W) + U conv(x, V) (exact, by linearity)
costs r / C_out of it.

Initialisation that keeps a pretrained primary network intact: H_a's last layer has zero
weight and outputs the given base weights through its bias; H_s's last layer has zero weight
and bias on U (or on the full Delta W), so Delta W = 0 exactly, while V starts random so that
U gets a gradient from the first step.
"""

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor, nn


@dataclass(frozen=True)
class ConvSpec:
    """A target convolution: its name in the depth predictor (``to_gaussians.0``) and shape."""

    name: str
    out_channels: int
    in_channels: int
    kernel_size: int

    @property
    def weight_shape(self) -> tuple[int, int, int, int]:
        k = self.kernel_size
        return (self.out_channels, self.in_channels, k, k)

    @property
    def fan_in(self) -> int:
        return self.in_channels * self.kernel_size**2

    @classmethod
    def of(cls, name: str, conv: nn.Conv2d) -> "ConvSpec":
        if conv.kernel_size[0] != conv.kernel_size[1] or conv.stride != (1, 1) or (
                conv.groups != 1 or conv.bias is None):
            raise ValueError(f"target layer {name} must be a square, stride-1, ungrouped conv "
                             f"with a bias, got {conv}")
        return cls(name, conv.out_channels, conv.in_channels, conv.kernel_size[0])


@dataclass
class LayerDelta:
    """Per-target change of one layer, for B*N targets: ``u`` [BN, O, r] and ``v``
    [BN, r, I, k, k] (rank-r form, ``v`` already scaled by 1/sqrt(fan_in)) or ``full``
    [BN, O, I, k, k]; ``bias`` [BN, O], or [BN, V, O] in the rank-r form: a bias change per
    (target, context view) pair (``train/studies/oracle_delta.py``'s probe; H_s never makes one)."""

    bias: Tensor
    u: Tensor | None = None
    v: Tensor | None = None
    full: Tensor | None = None


def split_weights(flat: Float[Tensor, " p"], specs: tuple[ConvSpec, ...]
                  ) -> list[tuple[Tensor, Tensor]]:
    """H_a's output -> (weight, bias) per layer."""
    out, i = [], 0
    for s in specs:
        n = math.prod(s.weight_shape)
        out.append((flat[i:i + n].view(s.weight_shape), flat[i + n:i + n + s.out_channels]))
        i += n + s.out_channels
    return out


def weights_size(specs: tuple[ConvSpec, ...]) -> int:
    return sum(math.prod(s.weight_shape) + s.out_channels for s in specs)


def delta_sizes(spec: ConvSpec, rank: int | None) -> dict[str, int]:
    """Sizes of one layer's part of H_s's output, in output order."""
    if rank is None:
        return {"full": math.prod(spec.weight_shape), "bias": spec.out_channels}
    return {"u": spec.out_channels * rank, "v": rank * spec.fan_in, "bias": spec.out_channels}


def split_deltas(flat: Float[Tensor, "t p"], specs: tuple[ConvSpec, ...], rank: int | None
                 ) -> list[LayerDelta]:
    """H_s's output for T targets -> a ``LayerDelta`` per layer."""
    t = flat.shape[0]
    out, i = [], 0
    for s in specs:
        parts = {}
        for key, n in delta_sizes(s, rank).items():
            parts[key] = flat[:, i:i + n]
            i += n
        if rank is None:
            out.append(LayerDelta(bias=parts["bias"],
                                  full=parts["full"].view(t, *s.weight_shape)))
        else:
            k = s.kernel_size
            out.append(LayerDelta(
                bias=parts["bias"], u=parts["u"].view(t, s.out_channels, rank),
                v=parts["v"].view(t, rank, s.in_channels, k, k) / math.sqrt(s.fan_in)))
    return out


class HyperMLP(nn.Module):
    """Linear(embed, hidden) - GELU - Linear(hidden, hidden) - GELU - Linear(hidden, out)."""

    def __init__(self, embed_dim: int, hidden: int, out_features: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(embed_dim, hidden), nn.GELU(),
                                 nn.Linear(hidden, hidden), nn.GELU(),
                                 nn.Linear(hidden, out_features))

    @property
    def last(self) -> nn.Linear:
        return self.net[-1]

    def forward(self, e: Float[Tensor, "... d"]) -> Float[Tensor, "... p"]:
        return self.net(e)


class AgnosticHypernetwork(nn.Module):
    """e_a (learnable, ``embed_dim``) -> H_a -> W: every target layer's weight and bias."""

    def __init__(self, specs: tuple[ConvSpec, ...], embed_dim: int, hidden: int,
                 base: Float[Tensor, " p"]):
        super().__init__()
        self.specs = specs
        self.embedding = nn.Parameter(torch.randn(embed_dim))
        self.hyper = HyperMLP(embed_dim, hidden, weights_size(specs))
        self.set_base(base)

    @torch.no_grad()
    def set_base(self, base: Float[Tensor, " p"]) -> None:
        """Make W equal ``base`` (flat weights and biases in ``specs`` order): zero last-layer
        weight, ``base`` as its bias."""
        if base.shape != self.hyper.last.bias.shape:
            raise ValueError(f"base weights must have {self.hyper.last.bias.numel()} values, "
                             f"got {base.numel()}")
        self.hyper.last.weight.zero_()
        self.hyper.last.bias.copy_(base)

    def forward(self) -> list[tuple[Tensor, Tensor]]:
        return split_weights(self.hyper(self.embedding), self.specs)


class SpecificHypernetwork(nn.Module):
    """e_s [T, embed_dim] -> H_s -> Delta W per target (rank-``rank`` factors or full)."""

    def __init__(self, specs: tuple[ConvSpec, ...], embed_dim: int, hidden: int,
                 rank: int | None, init_std: float = 0.0):
        super().__init__()
        self.specs, self.rank = specs, rank
        self.sizes = [delta_sizes(s, rank) for s in specs]
        self.hyper = HyperMLP(embed_dim, hidden, sum(sum(d.values()) for d in self.sizes))
        # Delta W = 0: zero rows for U / full and every bias delta. ``init_std`` > 0 draws the
        # U (or full) rows' weights from N(0, init_std^2) instead (biases stay zero): Delta W
        # then starts small but view-dependent, and the view-specific features get a
        # gradient from the first step (with exact zeros it is proportional to U, ~0).
        with torch.no_grad():
            for rows in self._gate_rows():
                self.hyper.last.weight[rows].zero_()
                self.hyper.last.bias[rows].zero_()
        if init_std > 0:
            self.open_gate(init_std)

    def _gate_rows(self) -> list[slice]:
        """The rows of the last layer that make U (or the full Delta W) and the bias deltas:
        what multiplies every view-specific gradient (the V rows are left out)."""
        rows, i = [], 0
        for d in self.sizes:
            for key, n in d.items():
                if key != "v":
                    rows.append(slice(i, i + n))
                i += n
        return rows

    @torch.no_grad()
    def open_gate(self, std: float, weight: float = 0.0) -> None:
        """Make Delta W depend on the embedding again: the weights of the last layer's U (or
        full) and bias-delta rows become ``weight`` times what they were plus N(0, std^2)
        noise (torch's global generator), their biases unchanged. With ``weight=1`` a trained
        H_s keeps what it learnt; at 0 (construction) it starts afresh. The view-specific
        branch's gradient is proportional to these rows (docs/model.md, "Is the branch
        live?"), so zero or tiny rows leave the ResNet, Proj and phi without one."""
        if not std >= 0:
            raise ValueError(f"std must be >= 0, got {std}")
        for rows in self._gate_rows():
            w = self.hyper.last.weight[rows]
            w.mul_(weight).add_(torch.empty_like(w).normal_(0.0, std))

    def forward(self, e: Float[Tensor, "t d"]) -> list[LayerDelta]:
        return split_deltas(self.hyper(e), self.specs, self.rank)
