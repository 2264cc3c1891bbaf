"""Where a command writes its output, checked before anything is written or started.

Every command that writes files (``run --out``, ``plot --out``, ``replay --out``, ``new
--dir``, ``calibrate -o/--plot``) checks its output paths first with :func:`check_output_file`
or :func:`check_output_folder`: a path that is a folder where a file is meant (or a file where
a folder is meant), a file in the way of a folder to create, or a folder nothing can be
created in (read-only, no permission, ``/proc``) is refused with one line naming the path and
the reason (an :class:`OutputPathError`: exit status 2), before a robot moves or a file is
written. Writability is probed for real -- a temporary file is created and removed in the
nearest folder that exists -- since permission bits say nothing to root or about read-only
mounts. The check creates no folder: a command that fails leaves nothing behind.

:func:`is_no_space` is the one rule for "the disk is full": only ``ENOSPC`` and ``EDQUOT``
say so, found on an ``OSError`` or in the text of a writer's error (foxglove-sdk reports
``... (os error 28)``, or logs ``Io(Os { code: 28 ...`` and then fails with an error that no
longer names it: :func:`watch_writer_errors` keeps that).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

from hilswarm.agents.errors import HilswarmError

#: errno values that mean the disk (or the user's quota) is full.
NO_SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})

#: How foxglove-sdk (Rust) writes an I/O error's number: ``... (os error 28)`` in an error's
#: text, ``Io(Os { code: 28, ...`` in what its writer logs.
_OS_ERROR = re.compile(r"\(os error (\d+)\)|\bOs \{ code: (\d+)")
_PROBE_PREFIX = ".hilswarm-probe-"


class OutputPathError(HilswarmError, ValueError):
    """An output path cannot be written (exit status 2), checked before anything started."""


def check_output_file(path: str | os.PathLike[str], *, what: str) -> None:
    """Refuse a file path that cannot be created (or replaced) before anything is written.

    Args:
        path: the file to write.
        what: what is written there, for the message (``"the recording"``).

    Raises:
        OutputPathError: ``path`` is a folder or not a regular file, a file is in the way of
            its folder, or nothing can be created in its folder.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"cannot write {what} to {path}: it is a directory")
    if path.exists() and not path.is_file():
        raise OutputPathError(f"cannot write {what} to {path}: it is not a regular file")
    _probe(_nearest_folder(path.parent, path, what), path, what)


def check_output_folder(path: str | os.PathLike[str], *, what: str) -> None:
    """Refuse a folder that cannot be written into (or created) before anything is written.

    Args:
        path: the folder to write into (created later, by the command, if missing).
        what: what is written there, for the message (``"the plots"``).

    Raises:
        OutputPathError: ``path`` (or a folder above it) is a file, or nothing can be created
            in it or in the nearest folder above it that exists.
    """
    path = Path(path)
    _probe(_nearest_folder(path, path, what), path, what)


def _nearest_folder(folder: Path, target: Path, what: str) -> Path:
    """``folder`` or the nearest folder above it that exists.

    Raises:
        OutputPathError: a file (not a folder) is found on the way up.
    """
    for candidate in (folder, *folder.absolute().parents):
        if candidate.is_dir():
            return candidate
        if candidate.exists() or candidate.is_symlink():
            shown = "it" if candidate == target else str(candidate)
            raise OutputPathError(f"cannot write {what} to {target}: {shown} is not a folder")
    raise OutputPathError(f"cannot write {what} to {target}: no folder above it exists")


def _probe(folder: Path, target: Path, what: str) -> None:
    """Create and remove a temporary file in ``folder``.

    Raises:
        OutputPathError: it cannot be created (the reason as the system says it).
    """
    try:
        handle, name = tempfile.mkstemp(prefix=_PROBE_PREFIX, dir=folder)
    except OSError as exc:
        where = "" if folder == target else f" in {folder}"
        reason = exc.strerror or str(exc)
        raise OutputPathError(
            f"cannot write {what} to {target}: cannot create files{where} ({reason})"
        ) from None
    os.close(handle)
    os.unlink(name)


def error_number(exc: BaseException) -> int | None:
    """The ``errno`` behind ``exc`` or an exception it was raised from (``None``: none given).

    An ``OSError``'s own ``errno`` counts; otherwise a writer's message ending in ``(os error
    N)`` (foxglove-sdk's I/O errors) gives ``N``.
    """
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno is not None:
            return current.errno
        number = errno_in_text(str(current))
        if number is not None:
            return number
        current = current.__cause__ or current.__context__
    return None


def errno_in_text(text: str) -> int | None:
    """The I/O error number a foxglove-sdk message names (``(os error N)``, ``Os { code: N``)."""
    match = _OS_ERROR.search(text)
    return None if match is None else int(match.group(1) or match.group(2))


def is_no_space(exc: BaseException | str) -> bool:
    """True if ``exc`` (an exception, or the text of a logged error) says the disk or the
    quota is full (``ENOSPC``, ``EDQUOT``), and only then."""
    number = errno_in_text(exc) if isinstance(exc, str) else error_number(exc)
    return number in NO_SPACE_ERRNOS


class WriterErrors(logging.Handler):
    """Keeps the full-disk error foxglove-sdk's writer logs: its later errors ("attempted
    another write after a write method failed") no longer name the cause."""

    def __init__(self) -> None:
        super().__init__(level=logging.WARNING)
        #: The first logged message that says the disk is full ("" if none).
        self.no_space = ""

    def emit(self, record: logging.LogRecord) -> None:
        if not self.no_space:
            text = record.getMessage()
            if is_no_space(text):
                self.no_space = text


@contextlib.contextmanager
def watch_writer_errors() -> Iterator[WriterErrors]:
    """What foxglove-sdk logs while the block writes (:class:`WriterErrors`)."""
    watcher = WriterErrors()
    foxglove_log = logging.getLogger("foxglove")
    foxglove_log.addHandler(watcher)
    try:
        yield watcher
    finally:
        foxglove_log.removeHandler(watcher)
