"""Errors raised on bad input.

Every message names the file, the field and what was expected, so that a user can fix the
input without reading a traceback. Command-line tools catch :class:`DataError` and print its
message alone.
"""

from __future__ import annotations

import os


class DataError(ValueError):
    """Bad or unsupported input data.

    Args:
        path: the offending file or folder (or ``None`` for in-memory data).
        problem: what is wrong, naming the field and the expectation.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
