"""The language autoencoder 512 → 3 → 512 (docs/method.md §6; LangSplat's layout).

```python
ae = LanguageAE()
code = ae.encode(features)   # [B, 512] -> [B, 3], unit vectors on S²
back = ae.decode(code)       # [B, 3] -> [B, 512], unit vectors
```

Encoder: Linear 512→256, then [BatchNorm, ReLU, Linear] to 128, 64, 32 and 3, then
L2-normalise. Decoder: Linear 3→16, then [ReLU, Linear] to 32, 64, 128, 256, 256 and
512, then L2-normalise. Features of another width D (SigLIP's 768) take D in place
of 512 at both ends. `decode` also takes codes with any leading shape (rendered
code maps [H, W, 3]).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

ENCODER_DIMS = (256, 128, 64, 32, 3)
DECODER_DIMS = (16, 32, 64, 128, 256, 256, 512)
NORM_EPS = 1e-12  # F.normalize's floor: a zero vector stays zero, never NaN


class LanguageAE(nn.Module):
    def __init__(
        self,
        in_dim: int = 512,
        encoder_dims: tuple[int, ...] = ENCODER_DIMS,
        decoder_dims: tuple[int, ...] | None = None,
    ):
        """Args:
        in_dim: the features' width (512 for CLIP ViT-B and MobileCLIP, 768 for
            SigLIP B, 64 for the tests' tiny model).
        encoder_dims: widths after the first layer, the code's last.
        decoder_dims: widths after the code, ending at in_dim; None: LangSplat's
            16 ... 256, 256 then in_dim.
        """
        super().__init__()
        if decoder_dims is None:
            decoder_dims = DECODER_DIMS[:-1] + (int(in_dim),)
        if decoder_dims[-1] != in_dim:
            raise ValueError(f"decoder must end at {in_dim}, got {decoder_dims}")
        enc: list[nn.Module] = [nn.Linear(in_dim, encoder_dims[0])]
        for a, b in zip(encoder_dims[:-1], encoder_dims[1:], strict=True):
            enc += [nn.BatchNorm1d(a), nn.ReLU(), nn.Linear(a, b)]
        dec: list[nn.Module] = [nn.Linear(encoder_dims[-1], decoder_dims[0])]
        for a, b in zip(decoder_dims[:-1], decoder_dims[1:], strict=True):
            dec += [nn.ReLU(), nn.Linear(a, b)]
        self.encoder = nn.Sequential(*enc)
        self.decoder = nn.Sequential(*dec)
        self.in_dim = in_dim
        self.code_dim = encoder_dims[-1]

    def encode(self, x: Tensor) -> Tensor:
        """[B, D] features → [B, C] unit codes."""
        return F.normalize(self.encoder(x), dim=-1, eps=NORM_EPS)

    def decode(self, h: Tensor) -> Tensor:
        """[..., C] codes → [..., D] unit features (any leading shape)."""
        lead = h.shape[:-1]
        out = self.decoder(h.reshape(-1, h.shape[-1]))
        return F.normalize(out, dim=-1, eps=NORM_EPS).reshape(*lead, -1)

    def forward(self, x: Tensor) -> Tensor:
        return self.decode(self.encode(x))

    @classmethod
    def from_state(cls, state: dict[str, Tensor]) -> LanguageAE:
        """Rebuild from a state dict (layer sizes read from the weights)."""
        enc = sorted(
            (int(k.split(".")[1]), v)
            for k, v in state.items()
            if k.startswith("encoder.") and k.endswith(".weight") and v.ndim == 2
        )
        dec = sorted(
            (int(k.split(".")[1]), v)
            for k, v in state.items()
            if k.startswith("decoder.") and k.endswith(".weight") and v.ndim == 2
        )
        if not enc or not dec:
            raise ValueError("not a LanguageAE state dict (no encoder/decoder weights)")
        model = cls(
            enc[0][1].shape[1],
            tuple(w.shape[0] for _, w in enc),
            tuple(w.shape[0] for _, w in dec),
        )
        model.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})
        model.eval()
        return model


def load_autoencoder(art: Any) -> LanguageAE:
    """The trained autoencoder stored in a train-ae artifact (anything with `.root()`)."""
    root = art.root()
    state = {
        k[4:]: torch.from_numpy(np.asarray(v))
        for k, v in root.items()
        if k.startswith("net.")
    }
    return LanguageAE.from_state(state)


__all__ = ["DECODER_DIMS", "ENCODER_DIMS", "LanguageAE", "load_autoencoder"]
