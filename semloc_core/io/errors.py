"""The one error type of a file semloc cannot use (its one-line descriptions: semloc_core/validation.py).

Every file format's error (``MapFormatError``, ``CameraFormatError``, ``DetectorModelError``, ...) is a
:class:`FileFormatError`: its message is one line naming the file, the field at fault (when there is one) and what
is wrong, e.g. ``map.json: objects[0].position[0]: Input should be a finite number (got inf)``. A worker whose file
is bad ends with exit code 2 and that line, and is not restarted (restarting cannot fix a file).
"""

from __future__ import annotations

from semloc_core.validation import one_line


class FileFormatError(ValueError):
    """A file that cannot be read, does not follow its format, or holds values outside its ranges. The message is
    made one line (see the module docstring); say the file, the field and what is wrong."""

    def __init__(self, message):
        super().__init__(one_line(message))
