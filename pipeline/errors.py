"""Errors shared by the stages: every message names the file it is about."""

from __future__ import annotations


class FileError(ValueError):
    """A problem with one input file; ``str(err)`` is ``"<file>: <reason>"``."""

    def __init__(self, path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")
