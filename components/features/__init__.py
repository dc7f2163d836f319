"""features — the ``features@<backbone>`` stage: image backbones and the per-shard cache of their output.

- :mod:`~components.features.backbones`: ``get_backbone(name, **options)``, ``available()``, the ``Backbone``
  interface; embedded (cues, tiny, cnn), packaged (efficientnet_lite0) and pretrained (resnet50, dinov2, clip)
  backbones.
- :mod:`~components.features.cache`: ``FeatureStore``, ``backbone_output``, ``open_features``,
  ``inputs_from_cached`` (cached output → the posterior's input ``x``), ``posterior_inputs`` (images → ``x``).
- :mod:`~components.features.options`: ``backbone_options(name, params, root)``.

Used by every stage but ``generate``, and by the ``pidc`` CLI (``options`` by ``features`` and ``train``
only; ``cache`` by all but the export stage).
"""

__all__ = ["backbones", "cache", "options"]
