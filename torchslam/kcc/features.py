"""Learned KCC channels: a small convolutional network on the orthographic images (``kcc.features=learned``).

The network sees what the hand-crafted channels see, the orthographic grey, depth and validity
of a keyframe map or a frame, and returns ``C = 2 + learned`` channels for the correlator:

    h, m = kcc_features_masked(grey, depth, valid)          # (B, 2, H, W) grey, depth; (B, 1, H, W) mask
    f = conv1x1(relu(conv3x3(relu(conv3x3([h, m])))))      # (B, learned, H, W)
    x = [h, standardize_masked(f, m)] * sqrt(w)[c],  w = C softmax(channel_logits)

- The hand-crafted channels pass through (a skip connection): the network can always fall
  back to them, and at initialisation (learned weights small) it nearly is them.
- Every channel has zero mean and unit variance over the mask before weighting, and the weights
  sum to ``C``, so the mean energy per element, which the Gaussian kernel's ``σ`` is relative
  to (``kernel_correlation`` divides by ``N = C H W``), is that of the hand-crafted channels:
  σ, λ and the PSR thresholds keep their meaning.
- The same code runs on any device; on the host the convolutions run channels-last (about 3x
  faster on CPU for these shapes). Weights are cast to the input's dtype and device, so a
  float64 input runs in float64 (``gradcheck``).

``load_feature_net`` reads a checkpoint written by ``scripts/train.py --what features``
(``torchslam.learn.save_checkpoint``); without a path it reads the weights that ship inside the
package (``PACKAGED_WEIGHTS``).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..cache import FifoCache
from ..checkpoint import load_checkpoint
from ..devices import is_host
from ..errors import ConfigError, DataFormatError
from .correlator import ChannelNorm, kcc_features_masked, standardize_masked

__all__ = ["PACKAGED_WEIGHTS", "KCCFeatureNet", "load_feature_net"]

PACKAGED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "kcc_features.pt"
MODULE_NAME = "KCCFeatureNet"


class KCCFeatureNet(nn.Module):
    """The learned KCC channels (see the module docstring).

    Args:
        learned: channels computed by the network, beside the two hand-crafted ones (``C = 2 + learned <= 8``).
        hidden: width of the two 3x3 convolutions.
        initial_weight: starting share ``w_c`` of each learned channel (the hand-crafted ones
            share the rest of ``C``); small, so that training starts near the hand-crafted channels.
    """

    def __init__(self, learned: int = 2, hidden: int = 4, initial_weight: float = 0.3):
        super().__init__()
        if not (isinstance(learned, int) and 1 <= learned <= 6):
            raise ConfigError(f"learned: expected 1 to 6 learned channels (C = 2 + learned <= 8), got {learned!r}")
        if not (isinstance(hidden, int) and 1 <= hidden <= 64):
            raise ConfigError(f"hidden: expected 1 to 64 hidden channels, got {hidden!r}")
        C = 2 + learned
        if not (0 < initial_weight < C / learned):
            raise ConfigError(f"initial_weight: expected a share in (0, {C / learned:g}), got {initial_weight!r}")
        self.learned = learned
        self.hidden = hidden
        self.conv1 = nn.Conv2d(3, hidden, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden, hidden, 3, padding=1)
        self.head = nn.Conv2d(hidden, learned, 1)
        # C softmax(logits): learned channels at initial_weight each, the two hand-crafted alike.
        rest = (C - learned * initial_weight) / 2
        logits = torch.tensor([0.0, 0.0] + [float(torch.log(torch.tensor(initial_weight / rest)))] * learned)
        self.channel_logits = nn.Parameter(logits)

    @property
    def channels(self) -> int:
        """C, the number of channels the correlator receives."""
        return 2 + self.learned

    def architecture(self) -> dict:
        """The constructor arguments that rebuild this network (stored in checkpoints)."""
        return {"learned": self.learned, "hidden": self.hidden}

    def channel_weights(self) -> Tensor:
        """(C,) share ``w_c`` of each channel's energy, summing to C: hand-crafted grey, depth, then the learned."""
        return self.channels * torch.softmax(self.channel_logits, dim=0)

    def forward(
        self,
        grey: Tensor,
        depth: Tensor,
        valid: Tensor,
        channel_norm: ChannelNorm | str = ChannelNorm.STANDARDIZE,
        fill_holes: int = 3,
    ) -> Tensor:
        """Compute the KCC channels of orthographic images.

        Args:
            grey: (B, H, W) grey values in [0, 1].
            depth: (B, H, W) depth, metres.
            valid: (B, H, W) bool validity.
            channel_norm: normalisation of the hand-crafted channels (``kcc_features``).
            fill_holes: their hole-filling window (``kcc_features``).

        Returns:
            (B, C, H, W) channels in the dtype of ``grey``, 0 where the pixel stays a hole.
        """
        h, m = kcc_features_masked(grey, depth, valid, channel_norm, fill_holes)
        dt = h.dtype
        x = torch.cat([h, m], dim=1)
        if is_host(x):
            x = x.contiguous(memory_format=torch.channels_last)
        # A no-op where the module was moved with its input (``NISlam`` moves its correlator).
        p = {name: v.to(device=x.device, dtype=dt) for name, v in self.named_parameters()}
        y = F.conv2d(x, p["conv1.weight"], p["conv1.bias"], padding=1)
        y = F.relu(y) if y.requires_grad else F.relu_(y)  # in place where no graph needs the input
        y = F.conv2d(y, p["conv2.weight"], p["conv2.bias"], padding=1)
        y = F.relu(y) if y.requires_grad else F.relu_(y)
        # The 1x1 head as a contraction over channels: a 1x1 convolution of channels-last data
        # takes a slow path on the CPU (about 3x slower here).
        f = torch.einsum("bchw,lc->blhw", y, p["head.weight"][:, :, 0, 0]) + p["head.bias"][:, None, None]
        scale = (self.channels * torch.softmax(p["channel_logits"], dim=0)).sqrt()
        f = standardize_masked(f.contiguous(), m) * scale[2:, None, None]
        return torch.cat([h * scale[:2, None, None], f], dim=1)


# (resolved path, modification time, size) -> (architecture, state dict): a run builds its
# correlator once, but tests and batch runs build many.
_LOADED: FifoCache[tuple[dict, dict]] = FifoCache(4)


def load_feature_net(path: str | os.PathLike | None = None) -> KCCFeatureNet:
    """Read the learned channels' network from a checkpoint (``None`` or ``""``: the packaged weights).

    Returns:
        A new ``KCCFeatureNet`` with the checkpoint's weights (float32, on the CPU), frozen
        (``requires_grad`` off, so that a run builds no autograd graph; ``requires_grad_()``
        makes it trainable again).

    Raises:
        DataFormatError: naming the file when it is missing, unreadable, or holds no
            ``KCCFeatureNet`` weights that fit its stored architecture.
    """
    path = Path(path).expanduser() if path else PACKAGED_WEIGHTS
    try:
        st = path.resolve().stat()
    except OSError:
        raise DataFormatError(f"{path}: no such checkpoint file (the learned KCC channels' weights)") from None
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    entry = _LOADED.get(key)
    if entry is None:
        doc = load_checkpoint(path)
        if doc["kind"] != "module" or doc.get("module") != MODULE_NAME:
            raise DataFormatError(
                f"{path}: holds {'config values' if doc['kind'] == 'config' else 'the weights of a ' + str(doc.get('module'))}, "
                f"not the learned KCC channels ({MODULE_NAME}; scripts/train.py --what features writes them)"
            )
        arch = doc["extra"].get("architecture", {})
        if not isinstance(arch, dict) or set(arch) - {"learned", "hidden"}:
            raise DataFormatError(f"{path}: architecture {arch!r} is not one of {MODULE_NAME}'s (keys learned, hidden)")
        entry = (dict(arch), dict(doc["state_dict"]))
        _LOADED.put(key, entry)
    arch, state = entry
    try:
        net = KCCFeatureNet(**arch)
        net.load_state_dict(state)
        net.requires_grad_(False)
    except (ConfigError, RuntimeError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataFormatError(f"{path}: the weights do not fit {MODULE_NAME}({arch}): {first}") from exc
    return net
