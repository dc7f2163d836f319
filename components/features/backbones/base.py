"""The backbone interface: an image → feature-vector map ``x ↦ f(x) ∈ ℝ^dim`` feeding the posterior flow.

In the paper's notation the flow models ``p(θ | f(x))`` where ``x`` is a front-camera image and ``f``
the backbone. A backbone is a :class:`torch.nn.Module` with

- ``name`` (registry key), ``dim`` (feature size), ``trainable`` (True: trained jointly with the
  flow as the NPE embedding network; False: frozen, its features can be cached on disk),
  ``input_size`` (the ``(H, W)`` in pixels its model input has);
- :meth:`preprocess` — uint8 RGB images ``(n, H, W, 3)`` → the model input tensor (size conversion
  included, announced once per backbone instance with :func:`warnings.warn`);
- :meth:`forward` — model input → features ``(n, dim)`` float32;
- :meth:`extract` — images → features as a float32 numpy array, batched, under inference mode;
- :meth:`mirror_inputs` — the posterior's inputs of the left-right mirrored images (training augmentation):
  flipped model inputs for a trainable backbone, permuted features (:meth:`mirror_index`) for a frozen one;
- :meth:`spared_index` — the features that are estimates of θ sharper than the training-input noise (spared by it);
- :meth:`fingerprint` — a hash of name, code version, configuration and weights, stored next to
  cached features to detect stale caches.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from components.core.checks import whole_number
from components.features.backbones.imageops import check_images, resize_area, to_unit_chw

__all__ = ["Backbone"]


class Backbone(nn.Module):
    """Base class of every backbone; see the module docstring for the contract.

    Subclasses set the class attributes, implement :meth:`forward` and :meth:`config`, and may
    override :meth:`_encode` (uint8 batch already at ``input_size`` → tensor; default: float32
    ``(n, 3, H, W)`` in [0, 1]) or :meth:`preprocess` altogether.
    """

    name: ClassVar[str] = ""
    #: version of the feature definition (code); bump it when features change for the same weights
    version: ClassVar[str] = "1"
    dim: int = 0
    trainable: bool = False
    input_size: tuple[int, int] = (128, 128)
    #: images per forward call within :meth:`extract`'s batches on a CPU (None: the whole batch). A forward that streams
    #: many full-image temporaries (the cues: ~60 of them) runs faster when a call's temporaries fit the CPU's caches.
    #: Set it only where each image's features are computed alone, so that they are the same to the bit in any chunk
    #: (the tiny, and the cues but for their wet-road block, whose detector's convolutions round by batch to ~1e-7; not
    #: the cnn, whose convolutions round by batch size; docs/studies/cache-sized-pieces.md)
    cpu_chunk: ClassVar[int | None] = None

    def __init__(self) -> None:
        super().__init__()
        self._resize_announced = False

    # -- configuration -------------------------------------------------------------------------------
    def config(self) -> dict[str, Any]:
        """The options that define the features (JSON-serialisable), e.g. for model cards."""
        return {}

    def extra_repr(self) -> str:
        return f"name={self.name!r}, dim={self.dim}, trainable={self.trainable}, input_size={self.input_size}"

    # -- input ---------------------------------------------------------------------------------------
    def _announce_resize(self, given: tuple[int, int], how: str) -> None:
        if not self._resize_announced:
            self._resize_announced = True
            warnings.warn(
                f"backbone {self.name!r}: converting {given[0]}×{given[1]} images to its input size "
                f"{self.input_size[0]}×{self.input_size[1]} ({how})",
                stacklevel=3,
            )

    def preprocess(self, images: np.ndarray) -> torch.Tensor:
        """uint8 RGB images ``(n, H, W, 3)`` (or one ``(H, W, 3)``) → the model input tensor.

        Images of another size than :attr:`input_size` are converted by area interpolation (said once
        per instance). Wrong dtype or channel count raises ``ValueError`` naming what is expected.
        """
        images = check_images(images, who=self.name)
        size = images.shape[1:3]
        if size != tuple(self.input_size):
            self._announce_resize(size, "area interpolation")
            images = resize_area(images, self.input_size)
        return self._encode(images)

    def _encode(self, images: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(to_unit_chw(images))

    # -- features ------------------------------------------------------------------------------------
    def _device(self) -> torch.device:
        for p in self.parameters():
            return p.device
        for b in self.buffers():
            return b.device
        return torch.device("cpu")

    def extract(self, images: np.ndarray, batch_size: int = 256, progress: bool = False) -> np.ndarray:
        """Features of a batch of images: float32 ``(n, dim)``, computed in batches in eval mode.

        Meant for frozen backbones (their features are cached); for a trainable one it gives the
        features of its current weights. The module's training mode is restored afterwards.
        """
        images = check_images(images, who=self.name)
        whole_number(f"{self.name}: batch_size", batch_size, low=1)
        n = images.shape[0]
        out = np.empty((n, self.dim), dtype=np.float32)
        starts = range(0, n, int(batch_size))
        if progress:
            from tqdm.auto import tqdm

            starts = tqdm(starts, desc=f"features@{self.name}", unit="batch")
        was_training = self.training
        device = self._device()
        self.eval()
        try:
            with torch.inference_mode():
                for s in starts:
                    x = self.preprocess(images[s : s + batch_size]).to(device)
                    out[s : s + x.shape[0]] = self._chunked(x).float().cpu().numpy()
        finally:
            self.train(was_training)
        return out

    def _chunked(self, x: torch.Tensor) -> torch.Tensor:
        """``self(x)``, in calls of :attr:`cpu_chunk` images on a CPU."""
        chunk = self.cpu_chunk
        if chunk is None or x.device.type != "cpu" or x.shape[0] <= chunk:
            return self(x)
        return torch.cat([self(x[i : i + chunk]) for i in range(0, x.shape[0], chunk)])

    # -- symmetry ------------------------------------------------------------------------------------
    def mirror_index(self) -> tuple[int, ...] | None:
        """The permutation of the features that a left-right mirror of the image makes: ``features(mirrored)[:, j] =
        features(image)[:, index[j]]`` (to float rounding); None where mirroring does not permute them (a learned or
        pretrained network's features). Frozen backbones with such a symmetry override it."""
        return None

    def spared_index(self) -> tuple[int, ...]:
        """The features the training-input noise spares (``train.input_noise_spared`` of its σ), in increasing order:
        a frozen network's estimates of θ with their own σ, sharper than the noise, which would cap the precision they
        carry (docs/studies/estimate-noise.md). ``()`` for a backbone without such features (the default)."""
        return ()

    def mirror_inputs(self, inputs: torch.Tensor) -> torch.Tensor:
        """The posterior's inputs of the left-right mirrored images (``TrainingConfig.mirror``): a trainable backbone's
        model inputs ``(n, C, H, W)`` flipped along W, a frozen backbone's features ``(n, dim)`` permuted by
        :meth:`mirror_index`. ``ValueError`` naming the backbone where neither applies."""
        if self.trainable:
            if inputs.ndim != 4:
                raise ValueError(f"{self.name}: mirroring expects model inputs (n, C, H, W), got {tuple(inputs.shape)}")
            return inputs.flip(-1)
        perm = getattr(self, "_mirror_perm", None)  # built once: this runs on every training batch
        if perm is None or perm.device != inputs.device:
            index = self.mirror_index()
            if index is None:
                raise ValueError(
                    f"backbone {self.name!r}: its features do not permute under a left-right mirror of the image, so "
                    "train.mirror cannot be used with it (set train.mirror: false)"
                )
            perm = self._mirror_perm = torch.as_tensor(index, device=inputs.device)
        if inputs.ndim != 2 or inputs.shape[1] != len(perm):
            raise ValueError(f"{self.name}: mirroring expects features (n, {len(perm)}), got {tuple(inputs.shape)}")
        return inputs[:, perm]

    # -- identity ------------------------------------------------------------------------------------
    def fingerprint(self) -> str:
        """SHA-256 (hex) of the name, code version, :meth:`config` and every parameter and buffer."""
        h = hashlib.sha256()
        head = {"name": self.name, "version": self.version, "dim": self.dim, "config": self.config()}
        h.update(json.dumps(head, sort_keys=True, default=str).encode("utf-8"))
        for key, tensor in sorted(self.state_dict().items()):
            t = tensor.detach().cpu().contiguous()
            h.update(f"{key}:{t.dtype}:{tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
        return h.hexdigest()
