"""Finding pretrained weights on this machine, fast, before any loading library is asked.

A pretrained backbone's weights come from, in order of precedence:

1. ``path`` — an explicit folder written by ``save_pretrained`` (or ``hf download --local-dir``);
2. ``pretrained_dir/<backbone name>`` — one sub-folder per backbone under a common directory
   (``backbones.pretrained_dir`` in ``params.yaml``);
3. the Hugging Face hub cache (``HF_HUB_CACHE`` / ``HF_HOME``) for the backbone's repo id.

A folder must hold ``config.json``, ``preprocessor_config.json`` and a weights file
(``model.safetensors``, ``pytorch_model.bin`` or their sharded ``*.index.json``). Loading is always
``local_files_only`` except when ``download=True`` was asked for a hub repo id and ``HF_HUB_OFFLINE`` is
not set. Whatever is missing raises :class:`MissingWeightsError` at once (a few file-system checks,
never the hub's retry loop), naming the backbone, where it looked and how to provide the weights.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["MissingWeightsError", "WeightsSource", "locate_weights", "hub_offline", "WEIGHT_FILES", "REQUIRED_FILES"]

#: files any one of which holds the weights
WEIGHT_FILES: tuple[str, ...] = (
    "model.safetensors",
    "model.safetensors.index.json",
    "pytorch_model.bin",
    "pytorch_model.bin.index.json",
)
#: files that must all be present
REQUIRED_FILES: tuple[str, ...] = ("config.json", "preprocessor_config.json")

_REPO_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*/[A-Za-z0-9][A-Za-z0-9._-]*$")


class MissingWeightsError(ValueError):
    """The weights of a pretrained backbone are not available locally (no silent random fallback)."""


@dataclass(frozen=True)
class WeightsSource:
    """Where to load from: a folder or a hub repo id, and whether the hub may be contacted."""

    #: a local folder path or a hub repo id, as passed to ``from_pretrained``
    location: str
    local_files_only: bool
    #: "path", "pretrained_dir" or "hub"
    kind: str
    #: the hub cache folder (``kind == "hub"``; None = the default cache)
    cache_dir: str | None = None


def hub_offline() -> bool:
    """True when ``HF_HUB_OFFLINE`` is set to a true value (1/true/yes/on)."""
    return os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in {"1", "true", "yes", "on"}


def _how_to(backbone: str, repo_id: str, folder: str) -> str:
    return (
        f"to provide them, on a machine with internet run `hf download {repo_id} --local-dir {folder}` "
        f"(or `huggingface_hub.snapshot_download('{repo_id}', local_dir='{folder}')`) and copy the folder here; "
        f"then pass path=... to get_backbone('{backbone}'), or set backbones.pretrained_dir in params.yaml "
        f"to its parent directory (with a sub-folder named '{backbone}'), or fill the hub cache and keep the default"
    )


def _check_folder(backbone: str, folder: Path, repo_id: str, kind: str) -> WeightsSource:
    if not folder.is_dir():
        raise MissingWeightsError(
            f"pretrained backbone {backbone!r}: no weights folder at {folder} ({kind}); "
            + _how_to(backbone, repo_id, str(folder))
        )
    missing = [f for f in REQUIRED_FILES if not (folder / f).is_file()]
    if not any((folder / f).is_file() for f in WEIGHT_FILES):
        missing.append(" or ".join(WEIGHT_FILES))
    if missing:
        raise MissingWeightsError(
            f"pretrained backbone {backbone!r}: the folder {folder} ({kind}) lacks {', '.join(missing)}; "
            + _how_to(backbone, repo_id, str(folder))
        )
    return WeightsSource(str(folder), True, kind)


def _hub_cache_dir(cache_dir: str | os.PathLike[str] | None) -> str:
    from huggingface_hub import constants

    return str(cache_dir) if cache_dir is not None else str(constants.HF_HUB_CACHE)


def _in_hub_cache(repo_id: str, filename: str, cache_dir: str | os.PathLike[str] | None) -> bool:
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:
        raise ImportError(
            "pretrained backbones need Hugging Face transformers: pip install 'pidc[pretrained]'"
        ) from None

    found = try_to_load_from_cache(repo_id, filename, cache_dir=cache_dir)
    return isinstance(found, str) and os.path.isfile(found)


def locate_weights(
    backbone: str,
    repo_id: str,
    *,
    path: str | os.PathLike[str] | None = None,
    pretrained_dir: str | os.PathLike[str] | None = None,
    download: bool = False,
    cache_dir: str | os.PathLike[str] | None = None,
) -> WeightsSource:
    """Decide where the weights of ``backbone`` are loaded from, or raise :class:`MissingWeightsError`.

    ``repo_id`` is the hub repository (``owner/name``) used when neither ``path`` nor
    ``pretrained_dir`` is given. ``download=True`` lets the hub be contacted for a repo that is not
    cached (ignored when ``HF_HUB_OFFLINE`` is set).
    """
    if path is not None:
        return _check_folder(backbone, Path(path).expanduser(), repo_id, "path")
    if pretrained_dir is not None:
        return _check_folder(backbone, Path(pretrained_dir).expanduser() / backbone, repo_id, "pretrained_dir")
    if not isinstance(repo_id, str) or not _REPO_ID.match(repo_id):
        raise ValueError(f"pretrained backbone {backbone!r}: repo_id must look like 'owner/name', got {repo_id!r}")
    cached = all(_in_hub_cache(repo_id, f, cache_dir) for f in REQUIRED_FILES) and any(
        _in_hub_cache(repo_id, f, cache_dir) for f in WEIGHT_FILES
    )
    cache = None if cache_dir is None else str(cache_dir)
    if cached:
        return WeightsSource(repo_id, True, "hub", cache)
    if download and not hub_offline():
        return WeightsSource(repo_id, False, "hub", cache)
    reason = "HF_HUB_OFFLINE is set" if (download and hub_offline()) else "download=False"
    raise MissingWeightsError(
        f"pretrained backbone {backbone!r}: {repo_id} is not in the Hugging Face cache {_hub_cache_dir(cache_dir)} "
        f"and no path or pretrained_dir was given ({reason}); "
        + _how_to(backbone, repo_id, f"<pretrained_dir>/{backbone}")
    )
