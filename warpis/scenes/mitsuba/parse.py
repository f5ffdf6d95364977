"""Mitsuba itself: its parser in the ``scalar_rgb`` variant with its log captured
(:class:`MitsubaSession`), and what it built read into numpy (an object's parameters and
description, a transform, a colour); how such values read in notes."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import fail

_SOURCE_PREFIX = re.compile(r"\[[\w.]+\.(?:cpp|h|py):\d+\]\s*")
_LOG_PREFIX = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\s+[A-Z]+\s+")


def _first_line(message: str) -> str:
    """The line of a Mitsuba message that says what went wrong: source locations
    stripped, a list under a header joined to it, context lines skipped."""
    lines: list[str] = []
    for raw in str(message).splitlines():
        line = _SOURCE_PREFIX.sub("", raw).strip()
        if not line:
            continue
        if line.startswith("- ") and lines:
            head = lines[-1]
            lines[-1] = head + (" " if head.endswith(":") else ", ") + line[2:]
        else:
            lines.append(line)
    for line in lines:
        if not line.endswith(":"):
            return line
    return lines[-1] if lines else "unknown error"


class MitsubaSession:
    """Mitsuba in its scalar_rgb variant with its log captured while warpis reads a
    scene; the caller's variant, log level and log appenders come back afterwards."""

    def __init__(self, file: Path):
        self.file = file
        try:
            import mitsuba
        except ImportError:
            raise fail(file, 'Mitsuba scenes need the optional mitsuba package: pip install "warpis[mitsuba]"') from None
        except OSError as exc:  # installed, but its libraries cannot load
            raise fail(file, f"Mitsuba cannot start: {exc}") from None
        self.mi = mitsuba
        self.log: list[tuple[Any, str]] = []

    def __enter__(self) -> MitsubaSession:
        mi = self.mi
        self.variant = mi.variant()
        try:
            mi.set_variant("scalar_rgb")
        except Exception as exc:  # a build without the variant
            raise fail(self.file, f"Mitsuba cannot run its scalar_rgb variant: {_first_line(str(exc))}") from None
        logger = mi.logger()
        self.level = logger.log_level()
        self.appenders = [logger.appender(i) for i in range(logger.appender_count())]
        log = self.log

        class Capture(mi.Appender):
            def append(self, level: Any, text: str) -> None:
                log.append((level, text))

            def log_progress(self, *args: Any) -> None:
                pass

        self.capture = Capture()
        logger.clear_appenders()
        logger.add_appender(self.capture)
        logger.set_log_level(mi.LogLevel.Warn)
        return self

    def __exit__(self, *exc: Any) -> None:
        mi = self.mi
        logger = mi.logger()
        logger.clear_appenders()
        for appender in self.appenders:
            logger.add_appender(appender)
        logger.set_log_level(self.level)
        if self.variant is not None and self.variant != "scalar_rgb":
            mi.set_variant(self.variant)

    def load(self) -> Any:
        """The scene, its shapes in the file's order and each one separate: Mitsuba's
        optimisations would merge meshes that share a BSDF and load them in any order."""
        mi = self.mi
        try:
            scene = mi.load_file(str(self.file), parallel=False, optimize=False)
        except Exception as exc:
            raise fail(self.file, f"Mitsuba cannot load it: {_first_line(str(exc))}") from None
        if not isinstance(scene, mi.Scene):
            raise fail(self.file, f"Mitsuba loads a {type(scene).__name__}, not a <scene>")
        return scene

    def warnings(self) -> list[str]:
        """Mitsuba's warnings while loading, as notes."""
        out = []
        for _, text in self.log:
            line = _first_line(_LOG_PREFIX.sub("", text))
            out.append(f"Mitsuba: {line}")
        return out


def object_parameters(mi: Any, obj: Any) -> dict[str, Any]:
    """The parameters Mitsuba exposes for ``obj`` (mi.traverse), by key."""
    traversed = mi.traverse(obj)
    out = {}
    for key in traversed.keys():
        try:
            out[key] = traversed[key]
        except TypeError:  # a parameter Mitsuba itself cannot read back (hair's unset sigma_a): never one warpis uses
            continue
    return out


def transform_matrix(transform: Any) -> np.ndarray:
    """A Mitsuba transform's matrix as (4, 4) float64."""
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)


def object_fields(text: str) -> tuple[str, dict[str, str]]:
    """Mitsuba's description of an object, ``Class[ key = value, ... ]`` → its class
    and the text of each top-level value."""
    name = re.match(r"\s*(\w*)", text).group(1)
    start = text.find("[")
    if start < 0:
        return name, {}
    depth, end = 0, len(text)
    for i in range(start, len(text)):
        if text[i] == "[":
            depth += 1
        elif text[i] == "]":
            depth -= 1
            if depth == 0:
                end = i
                break
    parts, depth, current = [], 0, []
    for ch in text[start + 1:end]:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append("".join(current))
            current = []
        else:
            current.append(ch)
    parts.append("".join(current))
    out = {}
    for part in parts:
        key, eq, value = part.partition("=")
        if eq:
            out[key.strip()] = value.strip()
    return name, out


def to_rgb(value: Any) -> np.ndarray:
    """A Mitsuba colour or float → (3,) float64."""
    a = np.array(value, dtype=np.float64).reshape(-1)
    return np.repeat(a, 3) if a.size == 1 else a[:3].copy()


def is_grey(rgb: np.ndarray) -> bool:
    """Whether a colour is the same in every channel."""
    return bool(np.all(rgb == rgb[0]))


def rgb_text(a: np.ndarray) -> str:
    """A colour as notes show it: one number when grey, else its three channels."""
    return "(" + ", ".join(f"{x:.6g}" for x in a) + ")" if not np.all(a == a[0]) else f"{a[0]:.6g}"


def vector_text(v: np.ndarray) -> str:
    """A point or direction as notes show it: (x, y, z)."""
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"
