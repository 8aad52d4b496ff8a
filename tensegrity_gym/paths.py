"""Output paths that never destroy an input: checked before a command does any work.

An output that resolves to one of the command's inputs (the same file through another name, a
symbolic or hard link, ``./``, ``..``) is refused, as is an output inside a folder that does not
exist or cannot be written, or one that names a folder.  Every message quotes the path as the
user gave it and names the option.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

__all__ = ["OutputPathError", "check_outputs"]


class OutputPathError(ValueError):
    """An output path that would overwrite an input or cannot be written."""


def _same_file(a: str, b: str) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)  # hard links, bind mounts
    except OSError:
        return False


def check_outputs(outputs: Mapping[str, str | None], inputs: Mapping[str, str | None]) -> None:
    """Raise :class:`OutputPathError` for an output that is an input, a folder, or unwritable.

    ``outputs`` and ``inputs`` map the option's name as the user typed it (``"--out"``,
    ``"the dataset"``) to the path given (``None``: not given).
    """
    given = {k: v for k, v in outputs.items() if v is not None}
    for opt, path in given.items():
        if path == "":
            raise OutputPathError(f"{opt}: an empty path cannot be written")
        for iopt, ipath in inputs.items():
            if ipath is not None and _same_file(path, ipath):
                raise OutputPathError(f"{opt} '{path}' is the same file as {iopt} '{ipath}': "
                                      "refusing to overwrite an input (choose another output path)")
        for other, opath in given.items():
            if other < opt and _same_file(path, opath):
                raise OutputPathError(f"{opt} '{path}' and {other} '{opath}' are the same file")
        folder = os.path.dirname(os.path.abspath(path))
        if os.path.isdir(path):
            raise OutputPathError(f"{opt} '{path}' is a folder, not a file")
        if not os.path.isdir(folder):
            raise OutputPathError(f"{opt} '{path}': folder '{os.path.dirname(path) or folder}' does not exist")
        if not os.access(folder, os.W_OK):
            raise OutputPathError(f"{opt} '{path}': folder '{os.path.dirname(path) or folder}' is not writable")
