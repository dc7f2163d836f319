"""domains — Tasks II and III: domains as weighted bags of images, and targets against sources.

- :mod:`~components.domains.absolute`: ``Domain`` (p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ)), ``ExponentialFilter`` (Task II).
- :mod:`~components.domains.relative`: simplex weights λ, the gap δ, the ODD decision (``relate``,
  ``OddDetector``, ``calibrate_on_sources``) (Task III).
- :mod:`~components.domains.difference`: where a target differs from the sources' fitted mixture, per parameter (W₁
  beside its in-ODD level) (``pidc relate``).
- :mod:`~components.domains.kernel`: a bag's weather as the kernel density of its images' posterior draws (Task III).
- :mod:`~components.domains.deconvolution`: the bag's maximum-likelihood weather distribution (Task II, ``deconvolved``).
- :mod:`~components.domains.scenarios`: known weather distributions (Gaussian mixtures, sub-boxes).
- :mod:`~components.domains.distances`: scores of an estimate against the truth (unbiased energy distance, W₁ and
  marginal HDRs per parameter) (Task II).
- :mod:`~components.domains.sweep`: the noise sweep over η (``NoiseSweep``, ``summarize_sweep``).
- :mod:`~components.domains.task2`, :mod:`~components.domains.task3`: what the ``task2`` and ``task3`` stages run;
  :mod:`~components.domains.task2_report`, :mod:`~components.domains.task3_report`: their plots and summaries.

Used by the ``task2`` and ``task3`` stages and the ``pidc`` CLI (``domain``, ``relate``).
"""

__all__ = [
    "absolute",
    "deconvolution",
    "difference",
    "distances",
    "kernel",
    "relative",
    "scenarios",
    "sweep",
    "task2",
    "task2_report",
    "task3",
    "task3_report",
]
