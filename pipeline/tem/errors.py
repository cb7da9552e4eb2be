"""Errors of the TEM stage: ``ValueError`` subclasses whose message names the file."""

from __future__ import annotations

from pipeline.errors import FileError


class TemError(FileError):
    """Base class; ``str(err)`` is ``"<file>: <reason>"``."""


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
