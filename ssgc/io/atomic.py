"""Writing files so that a crash or Ctrl-C never leaves a half-written one behind."""

from __future__ import annotations

import os
import re
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, TextIO

# mkstemp names: PREFIX + 8 characters of [a-z0-9_] + SUFFIX.  A process killed with SIGKILL (or a
# power cut) cannot remove its temporary file, so `--resume` recognises and removes them.
_TEMP_NAME = re.compile(r"\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp")


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write to a temporary file in the same directory, fsync, then rename over `path`.

    The rename is atomic on POSIX filesystems, so readers see the old file or the new one.
    """
    with atomic_writer(path) as f:
        f.write(text)


@contextmanager
def atomic_writer(path: str | Path) -> Iterator[TextIO]:
    """A text file that replaces `path` only when the block ends without an exception.

    Like `write_text_atomic`, but the text can be streamed, so a large output never has to be
    built as one string in memory first.
    """
    path = Path(path)
    umask = os.umask(0)
    os.umask(umask)
    tmp = None
    try:
        with _ctrl_c_deferred():  # no Ctrl-C between creating the file and knowing its name
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        with _ctrl_c_deferred():  # renamed, or still there to be removed: never both
            os.replace(tmp, path)
            tmp = None
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """`write_text_atomic` for binary files (GLB scenes, cached arrays)."""
    with atomic_binary_writer(path) as f:
        f.write(data)


@contextmanager
def atomic_binary_writer(path: str | Path) -> Iterator[BinaryIO]:
    """`atomic_writer` in binary mode."""
    path = Path(path)
    umask = os.umask(0)
    os.umask(umask)
    tmp = None
    try:
        with _ctrl_c_deferred():
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~umask)
        with _ctrl_c_deferred():
            os.replace(tmp, path)
            tmp = None
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


@contextmanager
def _ctrl_c_deferred() -> Iterator[None]:
    """Hold SIGINT during a few system calls; a Ctrl-C that arrives is delivered right after,
    as a KeyboardInterrupt at a point where the temporary file's fate is known."""
    can_block = hasattr(signal, "pthread_sigmask") and (
        threading.current_thread() is threading.main_thread()
    )
    if not can_block:
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def temp_target(filename: str) -> str | None:
    """The name of the file that a temporary file of `atomic_writer` was going to become."""
    m = _TEMP_NAME.fullmatch(filename)
    return m["target"] if m else None


def remove_stale_temps(directory: Path, is_ours: Callable[[str], bool]) -> int:
    """Delete the temporary files left in `directory` by a killed writer of files named
    `is_ours`; files of other names are never touched.  Returns how many were removed."""
    removed = 0
    for entry in os.scandir(directory):
        target = temp_target(entry.name)
        if target is not None and entry.is_file(follow_symlinks=False) and is_ours(target):
            Path(entry.path).unlink(missing_ok=True)
            removed += 1
    return removed
