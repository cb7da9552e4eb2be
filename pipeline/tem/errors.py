"""Errors of the TEM stage: ``ValueError`` subclasses whose message names the file."""
from __future__ import annotations


class TemError(ValueError):
    """Base class; ``str(err)`` is ``"<file>: <reason>"``."""

    def __init__(self, path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class TemReadError(TemError):
    """Unreadable, truncated or unsupported image file."""


class PixelSizeError(TemError):
    """No usable pixel size, or non-square pixels that cannot be corrected."""


class EmptyImageError(TemError):
    """Image without content (no pixels, or all pixels equal)."""


class NoTipError(TemError):
    """No tip silhouette found in the image."""


class ApexAtBorderError(TemError):
    """The apex region touches the image border."""
