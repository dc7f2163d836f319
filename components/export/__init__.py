"""export — the ``export`` stage and what reads its output: ONNX graphs in ``registry/<model>/``.

- :mod:`~components.export.onnx`: ``export_posterior(model, folder, card=…, exporter=…)``: context, log-density,
  sampling and whole-density graphs, checked against torch, and the model card.
- :mod:`~components.export.runtime`: ``OnnxPosterior``, the torch-free posterior (``log_prob``, ``sample``,
  ``context``/``on_context``) on onnxruntime.
- :mod:`~components.export.lookup`: models of the ``registry/`` folder by id or ``champion``, paired with their
  backbone (``load_registered``, ``RegisteredPosterior``, ``CHAMPION_POINTER``).

Used by the ``export`` stage (``onnx``), and by the ``evaluate``, ``task2`` and ``task3`` stages
and the ``pidc`` CLI (``runtime``, ``lookup``).
"""

__all__ = ["onnx", "runtime", "lookup"]
