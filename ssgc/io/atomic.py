"""Writing files so that a crash or Ctrl-C never leaves a half-written one behind."""

from __future__ import annotations

import hashlib
import os
import re
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

# mkstemp names: PREFIX + 8 characters of [a-z0-9_] + SUFFIX.  A process killed with SIGKILL (or a
# power cut) cannot remove its temporary file, so `--resume` recognises and removes them.
_TEMP_NAME = re.compile(r"\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp")
TEMP_EXTRA = len("..12345678.tmp")  # bytes a temporary file's name adds to its target's
NAME_MAX = 255  # bytes in one file name (Linux, macOS)
_DIGEST = 16  # hex digits of the hash that ends a shortened name


def fitted_name(name: str, extra: int) -> str:
    """`name`, or, when `extra` more bytes would make a file name over NAME_MAX, its start
    and a hash of all of it.  ssgc's own files beside an output (`.NAME.lock`, a temporary
    file, a journal) add to a name the user may have made as long as the system allows; the
    hash keeps the auxiliary files of two long names that share their start apart, and gives
    a resumed run the same names again."""
    raw = os.fsencode(name)
    if len(raw) + extra <= NAME_MAX:
        return name
    digest = hashlib.sha256(raw).hexdigest()[:_DIGEST]
    start = raw[: NAME_MAX - extra - _DIGEST - 1].decode("utf-8", "ignore")  # whole characters
    return f"{start}-{digest}"


BLOCK = 1 << 16  # bytes gathered before one write: streamed outputs are not kept in memory


def write_all(fd: int, data: bytes) -> None:
    """Write all of `data` to `fd`.  Every byte ssgc writes to a file goes through here, so the
    fault-injection tests can make a write fail at a chosen byte (tests/test_outputs.py)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


class TextSink:
    """UTF-8 text written to a file descriptor in blocks of `BLOCK` bytes, through `write_all`.

    The file descriptor is the caller's to close; `flush` pushes out what is gathered.
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self._parts: list[bytes] = []
        self._size = 0

    def write(self, text: str) -> int:
        self.write_bytes(text.encode("utf-8"))
        return len(text)

    def write_bytes(self, data: bytes) -> None:
        """Binary content (pictures, GLB files) through the same blocks."""
        self._parts.append(data)
        self._size += len(data)
        if self._size >= BLOCK:
            self.flush()

    def flush(self) -> None:
        data = b"".join(self._parts)
        self._parts.clear()
        self._size = 0
        if data:
            write_all(self.fd, data)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write to a temporary file in the same directory, fsync, then rename over `path`.

    The rename is atomic on POSIX filesystems, so readers see the old file or the new one.
    """
    with atomic_writer(path) as f:
        f.write(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """`write_text_atomic` for binary files (images): the bytes go under the text layer."""
    with atomic_writer(path) as f:
        f.write_bytes(data)


@contextmanager
def atomic_writer(path: str | Path) -> Iterator[TextSink]:
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
            fd, tmp = tempfile.mkstemp(
                prefix=f".{temp_part(path.name)}.", suffix=".tmp", dir=path.parent
            )
        try:
            sink = TextSink(fd)
            yield sink
            sink.flush()
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        with _ctrl_c_deferred():  # renamed, or still there to be removed: never both
            os.replace(tmp, path)
            tmp = None
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


@contextmanager
def _ctrl_c_deferred() -> Iterator[None]:
    """Hold a Ctrl-C during a few system calls; one that arrives is delivered right after, as
    a KeyboardInterrupt at a point where the temporary file's fate is known.

    Held at Python's level, not by the thread's signal mask: the kernel gives a SIGINT that
    the main thread blocks to another thread (a numerical library's worker), and Python
    then runs the handler in the main thread at its next bytecode whatever that thread's mask,
    which once raised inside `mkstemp` after the file was made and left it behind."""
    held = signal.getsignal(signal.SIGINT)
    # Only the main thread gets KeyboardInterrupt and may set handlers; a handler installed
    # by C code (None) could not be put back.
    if threading.current_thread() is not threading.main_thread() or held is None:
        yield
        return
    pressed: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, held)
    if pressed:
        signal.raise_signal(signal.SIGINT)  # to the handler of before: it raises here


def temp_part(name: str) -> str:
    """What a temporary file of `atomic_writer` for the file `name` holds of that name: all
    of it, or, for a name too long to take the temporary file's additions, a shortened one."""
    return fitted_name(name, TEMP_EXTRA)


def temp_target(filename: str) -> str | None:
    """The name of the file that a temporary file of `atomic_writer` was going to become (its
    `temp_part`, for a name too long to be held whole)."""
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


def remove_stale_temps_below(directory: Path) -> int:
    """`remove_stale_temps` for a tree only ssgc writes into (`ssg sample --export`'s
    OUTPUT/FORMAT/ and its meshes/): every temporary file of `atomic_writer` in it, at any
    depth (symbolic links are not followed).  Returns how many were removed."""
    if not directory.is_dir():
        return 0
    return sum(remove_stale_temps(Path(d), lambda target: True) for d, _, _ in os.walk(directory))
