"""Scenes: where a :class:`Scene` (plain numpy data, :mod:`.description`) comes from.

Sources: a TOML scene file (:mod:`.toml_source`), a Mitsuba 3 XML scene with its
receivers file (:mod:`.mitsuba`, needs the optional ``mitsuba`` package), arrays
(:meth:`Scene.from_arrays`), and the scenes bundled in ``meshes/`` by name.
:func:`load_scene` picks the source by the file's suffix (``SOURCES``); a new scene
source is one module producing a Scene and one entry there.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import resources
from pathlib import Path

from ..errors import fail
from ..limits import check_device
from .description import DIGEST_FIELDS, Receivers, Scene
from .mitsuba import check_channel, load_mitsuba
from .toml_source import load_toml, read_toml

__all__ = ["DIGEST_FIELDS", "SCENE_FILES", "SOURCES", "Receivers", "Scene", "bundled_scenes", "load_scene",
           "read_toml", "resolve_scene_path"]

# Suffix of a scene file → the function that reads it (path, device) → Scene.  The XML
# source also takes channel= and receivers= (see load_scene).
SOURCES: dict[str, Callable[..., Scene]] = {".toml": load_toml, ".xml": load_mitsuba}

# The file a scene folder holds, in the order they are looked for.
SCENE_FILES = ("scene.toml", "scene.xml")


def _bundled_root():
    """The installed ``warpis.meshes`` package, or ``meshes/`` beside a source checkout."""
    try:
        return resources.files("warpis.meshes")
    except ModuleNotFoundError:  # running from a checkout that was never pip-installed
        return Path(__file__).resolve().parents[2] / "meshes"

def _scene_file(folder):
    """The scene file of a folder (``SCENE_FILES``), or None."""
    for name in SCENE_FILES:
        if (folder / name).is_file():
            return folder / name
    return None

def bundled_scenes() -> list[str]:
    """Names of the scenes shipped in ``meshes/``."""
    root = _bundled_root()
    return sorted(p.name for p in root.iterdir() if p.is_dir() and _scene_file(p) is not None)

def resolve_scene_path(name_or_path: str | Path, base: Path | None = Path()) -> Path:
    """A path to a scene file (or to a folder holding ``scene.toml`` or ``scene.xml``),
    else a bundled scene's name → the scene file's path.

    Relative paths are taken from ``base`` (the working directory by default; a study's
    folder for its scenes); ``base=None`` accepts bundled names only.
    """
    text = str(name_or_path)
    if base is not None:
        candidate = base / text
        if candidate.is_file():
            return candidate
        if candidate.is_dir() and _scene_file(candidate) is not None:
            return _scene_file(candidate)
    if "/" not in text and "\\" not in text:
        bundled = _scene_file(_bundled_root() / text)
        if bundled is not None:
            return Path(str(bundled))
    names = ", ".join(bundled_scenes())
    where = text if base is None or base == Path() else base / text
    raise fail(where, f"no such scene file or bundled scene (bundled: {names})")

def load_scene(scene: str | Path, device: str = "cpu", *, channel: str | None = None,
               receivers: str | Path | None = None, camera: bool = False, width: int | None = None,
               height: int | None = None) -> Scene:
    """Load and validate a scene file (or a bundled scene by name).

    Parameters
    ----------
    scene
        A bundled scene's name (see :func:`bundled_scenes`) or the path of a scene file
        (a suffix of ``SOURCES``: ``.toml``, or ``.xml`` for a Mitsuba 3 scene).
    device
        Warp device the scene's kernels run on: ``"cpu"`` or ``"cuda"``/``"cuda:N"``.
    channel
        Mitsuba scenes: the colour channel, ``"r"``, ``"g"``, ``"b"`` or ``"y"``
        (luminance); None: the receivers file's, else ``"y"``.  TOML scenes are grey: any
        valid channel gives the same scene.
    receivers
        Mitsuba scenes: the receivers file (default ``<stem>.receivers.toml`` beside the
        XML).  A TOML scene lists its own receivers, so this is an error there.
    camera, width, height
        ``camera``: the receivers must be a camera's pixels (scenes/camera.py): a TOML
        scene's ``[receivers.camera]``, or a Mitsuba scene's perspective sensor (then its
        receivers file is optional).  ``width``/``height`` resize that camera.

    Returns
    -------
    Scene
        Plain numpy data; :func:`warpis.kernels.device.upload` puts it on its device.

    Raises
    ------
    WarpisError
        One line naming the file and the problem, for any invalid input.
    """
    check_device(device)
    file = resolve_scene_path(scene)
    suffix = file.suffix.lower()
    if suffix == ".xml":
        return load_mitsuba(file, str(device), channel=channel, receivers=None if receivers is None else Path(receivers),
                            camera=camera, width=width, height=height)
    if receivers is not None:
        raise fail(file, "a receivers file goes with a Mitsuba scene (.xml); a TOML scene lists its own [[receivers]]")
    if channel is not None:
        check_channel(channel, file)
    loaded = SOURCES.get(suffix, load_toml)(file, str(device), width=width, height=height)
    if camera and loaded.receivers.image is None:
        raise fail(file, "has no camera: an image needs [receivers.camera] in a TOML scene (docs/images.md)")
    return loaded
