"""Warnings that point at the caller's line, not at the library's internals."""

from __future__ import annotations

import os
import sys
import warnings

_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn(message, category)`` attributed to the first frame outside the jaxslam
    package: the user's call (``read_log(...)`` in their script, say), however deep inside the
    package the warning arose. (Python 3.12's ``skip_file_prefixes`` does this; 3.11 lacks it.)"""
    frame, level = sys._getframe(0), 1  # level 1: this function's own frame
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE_DIR):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
