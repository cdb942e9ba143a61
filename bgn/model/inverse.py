"""Inverse model (paper section "Inverse model definition and design", Eq. 6-10).

- A conditional normalising flow ``p(z | H̃_V,i)`` over the particle's *normalised* log-mass
  (1-D; context = the node feature width), trained by its negative log-likelihood: the forward
  KL of Eq. 8, with the log-density of Eq. 7. From zuko: ``"nsf"`` (neural spline flow) or
  ``"naf"`` (neural autoregressive flow, the paper's choice, Huang et al. 2018).
- Samples ``Z_K`` (one per particle, reparameterised so the relative-mass loss trains the flow
  and the encoder through them) feed the relative-mass decoder on edges, Eq. 9-10:
  ``h_ij = s(bilinear(z_i, z_j))``, then linear layers -> ``R̂_ij ≈ log m_i - log m_j``
  (normalised by its scale).

Both flows support ``rsample``: NSF inverts its splines in closed form; NAF inverts its monotone
network by bisection (about 25 network evaluations) and zuko differentiates that inverse
implicitly, which is why NAF is much slower to sample (DESIGN section 9).

The bilinear map acts on ``[z, 1]``: with 1-D ``z`` alone, ``z_i W z_j`` is symmetric in (i, j)
and cannot represent the antisymmetric ``z_i - z_j``; the constant channel adds the linear terms
``z_i`` and ``z_j`` (homogeneous coordinates) at no other cost.
"""

from __future__ import annotations

import torch
import zuko
from torch import nn
from torch.nn import functional as F

from bgn.model.message_passing import edge_chunks
from bgn.model.ops import activation

FLOWS = ("nsf", "naf")


def make_flow(kind: str, context: int, transforms: int, hidden: int) -> zuko.flows.Flow:
    """A 1-D conditional flow from zuko with ``transforms`` layers of width ``hidden``."""
    if kind == "nsf":
        return zuko.flows.NSF(1, context, transforms=transforms,
                              hidden_features=(hidden, hidden))
    if kind == "naf":
        return zuko.flows.NAF(1, context, transforms=transforms,
                              hidden_features=(hidden, hidden),
                              network={"hidden_features": (hidden, hidden)})
    raise ValueError(f"flow={kind!r}; choose one of {FLOWS}")


class InverseModel(nn.Module):
    """Flow over normalised log-mass given ``H̃_V`` plus the bilinear relative-mass decoder.

    Everything here is in normalised units (``Normalizer.log_mass`` / ``rel_log_mass``).
    """

    def __init__(self, context: int, flow: str = "nsf", transforms: int = 3, hidden: int = 64,
                 act: str = "silu") -> None:
        super().__init__()
        self.kind = flow
        self.flow = make_flow(flow, context, transforms, hidden)
        self.bilinear = nn.Bilinear(2, 2, hidden)     # Eq. 9 on [z, 1]
        self.act = activation(act)
        self.linear2 = nn.Linear(hidden, hidden)      # Eq. 10: W_Inv-Dec2
        self.linear3 = nn.Linear(hidden, 1)           # Eq. 10: W_Inv-Dec3
        self.edge_chunk: int | None = None            # set by PhysicsModel (its config)

    def forward(self, context: torch.Tensor, log_mass: torch.Tensor,
                noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Per particle: NLL of the normalised log-mass (Eq. 7-8) and one sample ``z_K``.

        ``noise`` (N,) is the base-distribution (standard normal) draw; pass it to make the
        sample reproducible (tests), else it is drawn here. Returns ``(nll (N,), z (N,))``.
        """
        dist = self.flow(context)  # the context network runs once for both uses
        nll = -dist.log_prob(log_mass[:, None])
        if noise is None:
            noise = torch.randn_like(log_mass)
        z = dist.transform.inv(noise[:, None]).squeeze(-1)  # rsample: differentiable
        return nll, z

    def relative(self, z: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        """Eq. 9-10 on edges: ``R̂_ij`` (E,) for edge j -> i (receiver minus sender); its
        (E, hidden) layers in chunks on very large graphs (``edge_chunk``)."""
        zt = torch.stack([z, torch.ones_like(z)], -1)              # [z, 1]
        return edge_chunks(self._relative, self.edge_chunk, (edge_index[1], edge_index[0]),
                           (zt,))

    def _relative(self, rcv: torch.Tensor, snd: torch.Tensor, zt: torch.Tensor) -> torch.Tensor:
        # s(Z_Kᵀ W1 Z_K): nn.Bilinear's own kernel is slow for 2 x 2 inputs on CPU; the same
        # map as a linear layer on the 4 products [z_i, 1] ⊗ [z_j, 1]
        outer = (zt.index_select(0, rcv)[:, :, None] * zt.index_select(0, snd)[:, None, :]
                 ).flatten(1)
        h = self.act(F.linear(outer, self.bilinear.weight.flatten(1), self.bilinear.bias))
        return self.linear3(self.act(self.linear2(h))).squeeze(-1)

    def sample_log_mass(self, context: torch.Tensor, n: int) -> torch.Tensor:
        """``n`` samples of every particle's normalised log-mass, shape (n, N)."""
        return self.flow(context).sample((n,)).squeeze(-1)
