"""Frozen pretrained backbones of the paper profile: ResNet-50, DINOv2 and CLIP (Hugging Face transformers).

What they see. The image, converted by each model's own image processor (read from the
``preprocessor_config.json`` saved with the weights, executed in torch by
:class:`~components.features.backbones.processor.ImageTransform`): a 128×128 render is upsampled to the
processor's size (e.g. shorter side 256 for ResNet-50 and DINOv2, 224 for CLIP; bicubic), centre
cropped to 224×224 and normalised with the model's mean/std. Features:

- ``resnet50`` — ``ResNetModel`` (default repo ``microsoft/resnet-50``): the globally average-pooled
  last stage, ``pooler_output`` flattened, dim 2048 (``hidden_sizes[-1]``).
- ``dinov2`` — ``Dinov2Model`` (default repo ``facebook/dinov2-small``, dim 384; ``facebook/dinov2-base``
  gives 768): ``pooler_output``, the layer-normalised CLS token.
- ``clip`` — ``CLIPVisionModel`` (default repo ``openai/clip-vit-base-patch32``): ``pooler_output``, the
  post-layer-normalised CLS token, dim 768 (``hidden_size``; before CLIP's projection to 512).

Why. These are the paper's three frozen backbones; features are cached once per dataset (the
``fingerprint`` hashes the model configuration, the preprocessing and every weight).

Weights are never downloaded implicitly and never replaced by random ones: see
:mod:`components.features.backbones.weights` (explicit folder, ``pretrained_dir/<name>``, or the hub cache;
:class:`~components.features.backbones.weights.MissingWeightsError` at once otherwise). ``transformers`` is
imported only when a pretrained backbone is built.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

import numpy as np
import torch

from components.features.backbones.base import Backbone
from components.features.backbones.imageops import check_images
from components.features.backbones.processor import ImageTransform
from components.features.backbones.weights import MissingWeightsError, WeightsSource, locate_weights

__all__ = ["PretrainedBackbone", "ResNet50Backbone", "Dinov2Backbone", "ClipBackbone"]


class PretrainedBackbone(Backbone):
    """A frozen Hugging Face vision model; subclasses name the architecture and the pooled output.

    Options: ``path`` (a folder with the weights), ``pretrained_dir`` (parent folder with one
    sub-folder per backbone name), ``repo_id`` (hub repository, default :attr:`default_repo`),
    ``download`` (allow contacting the hub for an uncached repo; default False), ``cache_dir`` (hub
    cache folder; default ``HF_HUB_CACHE``), ``device``.
    """

    version: ClassVar[str] = "1"
    trainable: bool = False
    default_repo: ClassVar[str] = ""
    #: the ``transformers`` model class name and the ``model_type`` values its config may have
    model_class: ClassVar[str] = ""
    model_types: ClassVar[tuple[str, ...]] = ()

    def __init__(
        self,
        path: str | os.PathLike[str] | None = None,
        pretrained_dir: str | os.PathLike[str] | None = None,
        repo_id: str | None = None,
        download: bool = False,
        cache_dir: str | os.PathLike[str] | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        self.repo_id = repo_id or self.default_repo
        source = locate_weights(
            self.name, self.repo_id, path=path, pretrained_dir=pretrained_dir, download=download, cache_dir=cache_dir
        )
        self.source = source
        self.model, processor = self._load(source)
        self.model.eval().requires_grad_(False).to(device)
        self.transform = ImageTransform.from_processor(processor)
        self.input_size = self.transform.output_size(128, 128)
        self.dim = self._feature_dim(self.model.config)

    # -- loading -------------------------------------------------------------------------------------
    def _load(self, source: WeightsSource) -> tuple[torch.nn.Module, Any]:
        try:
            import transformers
        except ImportError:
            raise ImportError(
                f"pretrained backbone {self.name!r} needs Hugging Face transformers: pip install 'pidc[pretrained]'"
            ) from None

        where = f"{source.location} ({source.kind})"
        kw: dict[str, Any] = {"local_files_only": source.local_files_only}
        if source.cache_dir is not None:
            kw["cache_dir"] = source.cache_dir
        try:
            config = transformers.AutoConfig.from_pretrained(source.location, **kw)
        except (OSError, ValueError) as e:
            raise MissingWeightsError(
                f"pretrained backbone {self.name!r}: cannot read config.json from {where}: {e}"
            ) from None
        if config.model_type not in self.model_types:
            raise ValueError(
                f"pretrained backbone {self.name!r}: {where} holds a {config.model_type!r} model, "
                f"expected one of {list(self.model_types)} ({self.model_class})"
            )
        model_cls = getattr(transformers, self.model_class)
        try:
            # the class reads its own config (CLIP's vision tower from a full CLIP checkpoint too)
            model = model_cls.from_pretrained(source.location, dtype=torch.float32, **kw)
            processor = transformers.AutoImageProcessor.from_pretrained(source.location, backend="pil", **kw)
        except OSError as e:
            raise MissingWeightsError(
                f"pretrained backbone {self.name!r}: cannot load weights from {where}: {e}"
            ) from None
        return model, processor

    def _feature_dim(self, config: Any) -> int:
        return int(config.hidden_size)

    def config(self) -> dict[str, Any]:
        model_config = {
            k: v
            for k, v in self.model.config.to_dict().items()
            if not k.startswith("_") and k != "transformers_version"
        }
        return {"model_class": self.model_class, "model": model_config, "transform": self.transform.as_dict()}

    def extra_repr(self) -> str:
        return super().extra_repr() + f", source={self.source.location!r}"

    # -- input and features --------------------------------------------------------------------------
    def preprocess(self, images: np.ndarray) -> torch.Tensor:
        """uint8 RGB ``(n, H, W, 3)`` → normalised float32 ``(n, 3, *input_size)`` per the model's processor."""
        images = check_images(images, who=self.name)
        h, w = images.shape[1:3]
        out_size = self.transform.output_size(h, w)
        if (h, w) != out_size:
            self._announce_resize((h, w), self.transform.describe(h, w))
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float()
        return self.transform(x).contiguous()

    def _pool(self, outputs: Any) -> torch.Tensor:
        return outputs.pooler_output

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised images ``(n, 3, H, W)`` (from :meth:`preprocess`) → pooled features ``(n, dim)``."""
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"{self.name}: expected a tensor (n, 3, H, W) from preprocess, got shape {tuple(x.shape)}")
        return self._pool(self.model(pixel_values=x)).reshape(x.shape[0], -1)


class ResNet50Backbone(PretrainedBackbone):
    """ResNet-50 (He et al. 2016), average-pooled last stage: dim 2048."""

    name: ClassVar[str] = "resnet50"
    default_repo: ClassVar[str] = "microsoft/resnet-50"
    model_class: ClassVar[str] = "ResNetModel"
    model_types: ClassVar[tuple[str, ...]] = ("resnet",)

    def _feature_dim(self, config: Any) -> int:
        return int(config.hidden_sizes[-1])


class Dinov2Backbone(PretrainedBackbone):
    """DINOv2 ViT (Oquab et al. 2023), layer-normalised CLS token: dim 384 (small) / 768 (base)."""

    name: ClassVar[str] = "dinov2"
    default_repo: ClassVar[str] = "facebook/dinov2-small"
    model_class: ClassVar[str] = "Dinov2Model"
    model_types: ClassVar[tuple[str, ...]] = ("dinov2",)


class ClipBackbone(PretrainedBackbone):
    """CLIP ViT-B/32 image tower (Radford et al. 2021), pooled CLS token: dim 768."""

    name: ClassVar[str] = "clip"
    default_repo: ClassVar[str] = "openai/clip-vit-base-patch32"
    model_class: ClassVar[str] = "CLIPVisionModel"
    model_types: ClassVar[tuple[str, ...]] = ("clip", "clip_vision_model")
