"""Torch model of the guidance policy: LSTM spatial encoder (or the paper's
occupancy-map baseline), the tanh head of docs/POLICY_SPEC.md, and a value head
for PPO. The numpy runtime (policy.runtime) reproduces `actor_mean` exactly.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from policy.features import ObsConfig

# The authors' code: distance edges [0, 3, 4, 5, 7, 10, 15, 20] x speed, plus one open
# bin beyond 20 so that there are 8 distance bins; 25 bearing bins over [-pi, pi).
OCC_DIST_EDGES = (0.0, 3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0)
OCC_BEARING_BINS = 25
OCC_OUTER_M = 30.0
"""Outer radius used only to give the open last distance bin a finite area."""


@dataclass(frozen=True)
class ModelConfig:
    """Network shape and observation encoding (the weights file's `config`)."""

    encoder: str = "lstm"
    """"lstm" (the paper's spatial encoding) or "occupancy" (the paper's baseline)."""
    encoding: str = "paper"
    """Neighbour tuple encoding, see policy.features.ObsConfig."""
    order: str = "index"
    """Neighbour order, see policy.features.ObsConfig."""
    dist_scale: float = 1.0
    """Distance normalisation (policy units)."""
    sense_range: float = 0.0
    """Neighbours beyond this are not observed (0 = unlimited)."""
    hidden: int = 63
    """LSTM hidden size; 63 + 1 goal feature = 64 head inputs in the paper."""
    head: tuple = (64, 64, 2)
    """Head layer sizes, the output layer last; every layer is tanh."""

    @property
    def obs(self) -> ObsConfig:
        return ObsConfig(self.encoding, self.order, self.dist_scale, self.sense_range)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["head"] = list(self.head)
        d["input"] = self.obs.input_size
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        keys = {f for f in cls.__dataclass_fields__}
        kw = {k: v for k, v in d.items() if k in keys}
        if "head" in kw:
            kw["head"] = tuple(kw["head"])
        return cls(**kw)


PAPER = ModelConfig()
"""The paper's network: encoding paper, index order, no normalisation."""
IMPROVED = ModelConfig(encoding="sincos", order="closest_last", dist_scale=10.0, sense_range=20.0)
"""sin/cos angles, nearest neighbour last, distances / 10, 20 m sense range."""
PRESETS = {"paper": PAPER, "improved": IMPROVED}


class LSTMEncoder(nn.Module):
    """Final hidden state of an LSTM run over the neighbour tuples (padded, gathered)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.lstm = nn.LSTM(cfg.obs.input_size, cfg.hidden, batch_first=True)
        self.out_size = cfg.hidden

    def forward(self, seq: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        b = seq.shape[0]
        if seq.shape[1] == 0:
            return torch.zeros(b, self.out_size, dtype=seq.dtype, device=seq.device)
        out, _ = self.lstm(seq)  # padding sits after each sequence, so out[len-1] is exact
        last = out[torch.arange(b, device=seq.device), (lengths - 1).clamp(min=0)]
        h = last * (lengths > 0).unsqueeze(-1).to(seq.dtype)
        return torch.tanh(h)


class OccupancyEncoder(nn.Module):
    """Occupancy map of 8 distance x 25 bearing bins, counts divided by bin area."""

    edges: torch.Tensor
    inv_area: torch.Tensor
    """Buffers (register_buffer): the inner distance edges, and 1 / each ring bin's area."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        edges = torch.tensor(OCC_DIST_EDGES[1:], dtype=torch.float32)
        self.register_buffer("edges", edges)
        outer = torch.tensor((*OCC_DIST_EDGES, OCC_OUTER_M), dtype=torch.float32)
        ring = math.pi * (outer[1:] ** 2 - outer[:-1] ** 2) / OCC_BEARING_BINS
        self.register_buffer("inv_area", 1.0 / ring)
        self.out_size = len(OCC_DIST_EDGES) * OCC_BEARING_BINS

    def forward(self, seq: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        b, k = seq.shape[:2]
        nd = len(OCC_DIST_EDGES)
        if k == 0:
            return torch.zeros(b, self.out_size, dtype=seq.dtype, device=seq.device)
        d = seq[..., 0] * self.cfg.dist_scale
        psi = seq[..., 1] if self.cfg.encoding == "paper" else torch.atan2(seq[..., 1], seq[..., 2])
        di = torch.bucketize(d.contiguous(), self.edges, right=True).clamp(max=nd - 1)
        bi = (
            ((psi + math.pi) / (2 * math.pi) * OCC_BEARING_BINS)
            .long()
            .clamp(0, OCC_BEARING_BINS - 1)
        )
        valid = torch.arange(k, device=seq.device)[None, :] < lengths[:, None]
        w = valid.to(seq.dtype) * self.inv_area[di]
        grid = torch.zeros(b, self.out_size, dtype=seq.dtype, device=seq.device)
        grid.scatter_add_(1, di * OCC_BEARING_BINS + bi, w)
        return grid


class ActorCritic(nn.Module):
    """Encoder, tanh actor head (exported) and a value head (training only)."""

    def __init__(self, cfg: ModelConfig, init_log_std: float = math.log(0.6)):
        super().__init__()
        self.cfg = cfg
        self.encoder = LSTMEncoder(cfg) if cfg.encoder == "lstm" else OccupancyEncoder(cfg)
        z = self.encoder.out_size + cfg.obs.goal_size
        layers: list[nn.Linear] = []
        for size in cfg.head:
            layers.append(nn.Linear(z, size))
            z = size
        self.head = nn.ModuleList(layers)
        zin = self.encoder.out_size + cfg.obs.goal_size
        self.critic = nn.Sequential(
            nn.Linear(zin, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 1)
        )
        self.log_std = nn.Parameter(torch.full((cfg.head[-1],), init_log_std))
        for lin in layers:
            nn.init.orthogonal_(lin.weight, math.sqrt(2))
            nn.init.zeros_(lin.bias)
        nn.init.orthogonal_(layers[-1].weight, 0.01)

    def features(self, seq, lengths, goal):
        return torch.cat([self.encoder(seq, lengths), goal], dim=-1)

    def actor_mean(self, seq, lengths, goal) -> torch.Tensor:
        """Unclipped tanh head output (B, 2): the deterministic action before |a| <= 1."""
        z = self.features(seq, lengths, goal)
        for lin in self.head:
            z = torch.tanh(lin(z))
        return z

    def forward(self, seq, lengths, goal):
        """(mean, value): one pass for PPO; the value sees the encoder without gradient."""
        f = self.features(seq, lengths, goal)
        z = f
        for lin in self.head:
            z = torch.tanh(lin(z))
        return z, self.critic(f.detach()).squeeze(-1)


def parameter(module: nn.Module, name: str) -> torch.Tensor:
    """`module`'s parameter `name`, typed (attribute access on a Module is Tensor | Module)."""
    return module.get_parameter(name)


def clip_unit(a: torch.Tensor) -> torch.Tensor:
    """a / max(|a|, 1)."""
    return a / a.norm(dim=-1, keepdim=True).clamp(min=1.0)


def state_arrays(model: ActorCritic) -> dict:
    """Float32 arrays in the weights-file layout of docs/POLICY_SPEC.md (lstm only)."""
    out = {}
    if isinstance(model.encoder, LSTMEncoder):  # the encoder is an LSTM iff cfg.encoder says so
        lstm = model.encoder.lstm
        out["lstm.weight_ih"] = parameter(lstm, "weight_ih_l0").detach().cpu().numpy()
        out["lstm.weight_hh"] = parameter(lstm, "weight_hh_l0").detach().cpu().numpy()
        bias = parameter(lstm, "bias_ih_l0") + parameter(lstm, "bias_hh_l0")
        out["lstm.bias"] = bias.detach().cpu().numpy()
    for k, lin in enumerate(model.head):
        out[f"head.{k}.weight"] = parameter(lin, "weight").detach().cpu().numpy()
        out[f"head.{k}.bias"] = parameter(lin, "bias").detach().cpu().numpy()
    return {k: np.asarray(v, dtype=np.float32) for k, v in out.items()}


def load_actor_arrays(model: ActorCritic, arrays: dict) -> None:
    """The weights-file arrays (docs/POLICY_SPEC.md, lstm) into `model`'s LSTM and head; the
    inverse of `state_arrays` (the one combined bias goes to bias_ih, bias_hh is zero)."""
    if not isinstance(model.encoder, LSTMEncoder):
        raise ValueError(f"weights files hold an LSTM encoder; this model's is {model.cfg.encoder}")
    lstm = model.encoder.lstm
    with torch.no_grad():
        parameter(lstm, "weight_ih_l0").copy_(torch.from_numpy(arrays["lstm.weight_ih"]))
        parameter(lstm, "weight_hh_l0").copy_(torch.from_numpy(arrays["lstm.weight_hh"]))
        parameter(lstm, "bias_ih_l0").copy_(torch.from_numpy(arrays["lstm.bias"]))
        parameter(lstm, "bias_hh_l0").zero_()
        for k, lin in enumerate(model.head):
            parameter(lin, "weight").copy_(torch.from_numpy(arrays[f"head.{k}.weight"]))
            parameter(lin, "bias").copy_(torch.from_numpy(arrays[f"head.{k}.bias"]))
