"""Colour: warpis is monochrome, so Mitsuba's linear sRGB becomes one channel
(``CHANNELS``: r, g, b, or the luminance y), chosen by the caller or the receivers file."""

from __future__ import annotations

from typing import Any

from ...errors import fail

# Weights of linear sRGB's channels in warpis's one channel.  y is the luminance with the
# weights Mitsuba itself uses (mi.luminance).
CHANNELS: dict[str, tuple[float, float, float]] = {
    "r": (1.0, 0.0, 0.0),
    "g": (0.0, 1.0, 0.0),
    "b": (0.0, 0.0, 1.0),
    "y": (0.212671, 0.715160, 0.072169),
}
CHANNEL_WORDS = {
    "r": "the red channel of linear sRGB",
    "g": "the green channel of linear sRGB",
    "b": "the blue channel of linear sRGB",
    "y": "luminance of linear sRGB, 0.212671 R + 0.715160 G + 0.072169 B",
}
DEFAULT_CHANNEL = "y"


def check_channel(channel: Any, where: object) -> str:
    """``channel`` if it names one of ``CHANNELS``, else a one-line error."""
    if not isinstance(channel, str) or channel not in CHANNELS:
        raise fail(where, f"channel {channel!r}: expected one of {', '.join(CHANNELS)} (r, g, b of linear sRGB, "
                          f"or y, its luminance)")
    return channel
