"""simulate — the first stage (``generate``): front-camera images under CARLA weathers, and the dataset of them.

Public API, by module (imported from the module itself, so that a stage that only reads the dataset does not
import the renderer):

- :mod:`~components.simulate.base`: ``Simulator`` (the protocol: ``render(weather, scene_seed) → (H, W, 3) uint8``)
  and ``make_simulator(config)``.
- :mod:`~components.simulate.procedural`: ``ProceduralSimulator(height, width)``, the embedded physical renderer.
- :mod:`~components.simulate.resized`: ``ResizedRenders``, its camera-like renders (each scene rendered larger and
  area-resized: ``simulator.render_sizes``), and the exact ``area_resize``.
- :mod:`~components.simulate.carla`: ``CarlaSimulator``, the CARLA client backend (needs the ``carla`` extra).
- :mod:`~components.simulate.dataset`: deterministic plans, shards, receipts and manifests of the train/val/test
  splits (``plan_split``, ``render_shard``, ``open_split``, ``Split``).
- :mod:`~components.simulate.labels`: the labels file of a recorded folder (read and checked; also the monitoring's).
- :mod:`~components.simulate.recorded`: recorded datasets, imported into the shards (``simulator.backend: recorded``),
  and ``record``, which writes such a folder from any simulator (``pidc record``).
- :mod:`~components.simulate.contact_sheet`: the contact sheet of the ``generate`` stage.
- :mod:`~components.simulate.in_memory`: ``render_split``, a split's plan rendered into memory without shards (the
  cue networks' training scripts and the benchmarks).

Used by the ``generate`` stage; ``dataset`` also by every later stage but the export stages, the simulators (``base``,
``procedural``, ``resized``, ``carla``) also by ``evaluate`` (PPCs) and ``task2`` (its bag); the ``pidc`` CLI imports all of it.
"""

__all__ = ["base", "procedural", "resized", "carla", "dataset", "labels", "recorded", "contact_sheet", "in_memory"]
