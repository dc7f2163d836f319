"""Where a project's pipeline state lives: data, feature caches, models, the exported registry and the reports.

Every stage (``flows/``) finds its folders here, relative to the params file's folder (the project root), so no flow
has to import another to learn where the previous stage wrote.

Used by every stage (through :mod:`flows.stage`; ``task3`` also in :mod:`components.domains.task3`); the ``pidc`` CLI
does not import it (it takes its folders from the command line).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from components.core.config import Params

__all__ = ["ProjectPaths"]


@dataclass(frozen=True)
class ProjectPaths:
    """The folders of the project whose params file is ``params_file``.

    Attributes:
        root: the project root (the params file's folder).
        data: the simulated dataset (``data.root``, relative to ``root`` unless absolute).
    """

    root: Path
    data: Path

    @classmethod
    def of(cls, params: Params, params_file: str | Path) -> ProjectPaths:
        root = Path(params_file).resolve().parent
        data = Path(params.data.root)
        return cls(root=root, data=data if data.is_absolute() else root / data)

    @property
    def features(self) -> Path:
        """``features/``: one cache folder per backbone (the ``features@<backbone>`` stages)."""
        return self.root / "features"

    @property
    def models(self) -> Path:
        """``models/``: one folder per trained model (the ``train`` stage)."""
        return self.root / "models"

    @property
    def registry(self) -> Path:
        """``registry/``: one exported ONNX folder per model (the ``export`` stage)."""
        return self.root / "registry"

    def kept(self, *parts: str) -> Path:
        """``.cache/<parts…>``: results a stage keeps between its runs outside its DVC outputs (which DVC removes when
        the stage starts), each keyed by what made it (inputs, settings, :func:`components.core.code.code_fingerprint`
        of its code), so a killed or repeated run reuses what is finished and nothing stale."""
        return self.root.joinpath(".cache", *parts)

    def reports(self, *parts: str) -> Path:
        """``reports/<parts…>``: metrics and plots of the stages."""
        return self.root.joinpath("reports", *parts)

    def resolve(self, path: str | Path) -> Path:
        """``path`` relative to the project root, unless absolute."""
        p = Path(path)
        return p if p.is_absolute() else self.root / p
