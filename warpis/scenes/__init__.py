"""Scenes: where a :class:`Scene` (plain numpy data, :mod:`.description`) comes from.

Sources: a TOML scene file (:mod:`.toml_source`), arrays (:meth:`Scene.from_arrays`),
and the scenes bundled in ``meshes/`` by name.  :func:`load_scene` picks the source by
the file's suffix (``SOURCES``); a new scene source is one module producing a Scene and
one entry there.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import resources
from pathlib import Path

from ..errors import fail
from ..kernels.device import check_device
from .description import DIGEST_FIELDS, Receivers, Scene
from .toml_source import load_toml, read_toml

__all__ = ["DIGEST_FIELDS", "SOURCES", "Receivers", "Scene", "bundled_scenes", "load_scene", "read_toml",
           "resolve_scene_path"]

# Suffix of a scene file → the function that reads it (path, device) → Scene.
SOURCES: dict[str, Callable[[Path, str], Scene]] = {".toml": load_toml}


def _bundled_root():
    """The installed ``warpis.meshes`` package, or ``meshes/`` beside a source checkout."""
    try:
        return resources.files("warpis.meshes")
    except ModuleNotFoundError:  # running from a checkout that was never pip-installed
        return Path(__file__).resolve().parents[2] / "meshes"

def bundled_scenes() -> list[str]:
    """Names of the scenes shipped in ``meshes/``."""
    root = _bundled_root()
    return sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "scene.toml").is_file())

def resolve_scene_path(name_or_path: str | Path, base: Path | None = Path()) -> Path:
    """A path to a scene file (or to a folder holding ``scene.toml``), else a bundled
    scene's name → the scene file's path.

    Relative paths are taken from ``base`` (the working directory by default; a study's
    folder for its scenes); ``base=None`` accepts bundled names only.
    """
    text = str(name_or_path)
    if base is not None:
        candidate = base / text
        if candidate.is_file():
            return candidate
        if candidate.is_dir() and (candidate / "scene.toml").is_file():
            return candidate / "scene.toml"
    bundled = _bundled_root() / text / "scene.toml"
    if "/" not in text and "\\" not in text and bundled.is_file():
        return Path(str(bundled))
    names = ", ".join(bundled_scenes())
    where = text if base is None or base == Path() else base / text
    raise fail(where, f"no such scene file or bundled scene (bundled: {names})")

def load_scene(scene: str | Path, device: str = "cpu") -> Scene:
    """Load and validate a scene file (or a bundled scene by name).

    Parameters
    ----------
    scene
        A bundled scene's name (see :func:`bundled_scenes`) or the path of a scene file
        (a suffix of ``SOURCES``: ``.toml``).
    device
        Warp device the scene's kernels run on: ``"cpu"`` or ``"cuda"``/``"cuda:N"``.

    Returns
    -------
    Scene
        Plain numpy data; ``scene.data`` and ``scene.receiver_data`` upload it on first use.

    Raises
    ------
    WarpisError
        One line naming the file and the problem, for any invalid input.
    """
    check_device(device)
    file = resolve_scene_path(scene)
    return SOURCES.get(file.suffix.lower(), load_toml)(file, str(device))
