"""Every file a command writes, checked before the work starts and written without damage.

The rules (docs/robustness.md, "Outputs"), for every output of every command (`-o`,
`--report`, journals, sample directories, and the commands still to come):

- An output is checked before any work: it is not a directory (unless a directory is asked
  for), its directory exists and accepts a new file, it is not one of the command's inputs
  (unless the command documents an in-place update), and no two outputs are one file.  A name
  ending in `/` (`-o notes.txt/`) asks for a directory: refused unless it is one.
- A regular file (or a name not yet there) is replaced atomically: written to a temporary file
  beside it and renamed over it (`ssgc.io.atomic`).  A symbolic link is followed: the file it
  points to is replaced and the link stays a link.
- A character device (`/dev/null`, `/dev/full`), a FIFO, and `-`, `/dev/stdout` (standard
  output) are streams: written in place, never renamed over, never journalled.
- A failed write (a full disk, an I/O error, a read-only file system, a denied permission) is a
  user-facing error naming the output (exit 1); the temporary file is removed, so the output is
  its old content or absent.
- One writer per output: a lock (``flock`` on a lock file beside it, or in the directory) refuses
  a second run writing the same output while the first one runs.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import sys
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ssgc.errors import SsgError, one_line
from ssgc.io.atomic import TextSink, atomic_writer, fitted_name, write_all, write_bytes_atomic

STDOUT_NAMES = frozenset({"-", "/dev/stdout", "/dev/fd/1", "/proc/self/fd/1"})

# Errors of the machine, not of ssgc: a message and exit 1, never "a bug in ssgc".
ENVIRONMENT_ERRNOS = frozenset(
    getattr(errno, name)
    for name in (
        "ENOSPC", "EDQUOT", "EIO", "EROFS", "EACCES", "EPERM", "EFBIG", "EMFILE", "ENFILE",
        "ENOMEM", "ENXIO", "ENODEV", "ESTALE", "ETXTBSY", "EBUSY", "ENOLCK", "EISDIR",
        "ENOTDIR", "ENAMETOOLONG", "ELOOP",
    )
    if hasattr(errno, name)
)  # fmt: skip


@dataclass(frozen=True)
class Output:
    """One output file of a command, as checked by `check_output`."""

    path: Path  # as the user named it (for messages)
    target: Path  # what is written: the file a symbolic link points to, or the device itself
    what: str  # "output", "report", ...: how messages name it
    stream: bool = False  # a device, a FIFO or standard output: written in place
    stdout: bool = False  # standard output (`-`, `/dev/stdout`)

    @property
    def name(self) -> str:
        return "<stdout>" if self.stdout and str(self.path) == "-" else str(self.path)

    def fail(self, exc: OSError, note: str = "") -> SsgError:
        reason = exc.strerror or str(exc)  # an OSError raised with a message only has no strerror
        return SsgError.single(f"cannot write the {self.what}: {reason}{note}", self.name)


def check_output(
    path: str | Path,
    what: str = "output",
    inputs: Iterable[str | Path] = (),
    in_place: Iterable[str | Path] = (),
    others: Iterable[Output] = (),
) -> Output:
    """Check that `path` can be written before any work is done; raise `SsgError` if not.

    `inputs` are the command's input files and directories: the output must not be one of them
    (nor a `.json` file inside an input directory, where it would be read as a scene next time),
    except those in `in_place`, which the command updates on purpose.  `others` are the
    command's outputs checked before this one: two outputs must be two files.
    """
    if not isinstance(path, str | Path):  # the API's callers (Scene.save, .render)
        raise TypeError(f"the {what}'s path must be a str or Path, got {type(path).__name__}")
    _refuse_slash_on_file(path)
    path = _usable_name(path, what)
    if str(path) in STDOUT_NAMES:
        out = Output(path, path, what, stream=True, stdout=True)
        _check_distinct(out, others)
        return out
    try:
        st: os.stat_result | None = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise SsgError.single(f"cannot write the {what}: {exc.strerror}", str(path)) from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise SsgError.single(
            f"the {what} is a directory; give a file name (such as {path / 'NAME'})", str(path)
        )
    if st is not None and (stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode)):
        if not os.access(path, os.W_OK):
            raise SsgError.single(f"cannot write the {what}: permission denied", str(path))
        out = Output(path, path, what, stream=True)
    elif st is not None and not stat.S_ISREG(st.st_mode):
        raise SsgError.single(
            f"the {what} is not a regular file, a character device or a FIFO", str(path)
        )
    else:
        target = Path(os.path.realpath(path))
        _check_directory_accepts_files(target.parent, what, str(path))
        out = Output(path, target, what)
    _check_not_an_input(out, inputs, in_place)
    _check_distinct(out, others)
    return out


def _usable_name(path: str | Path, what: str) -> Path:
    if "\0" in str(path):
        raise SsgError.single(f"the {what}'s name holds a NUL character", one_line(str(path)))
    return Path(path)


# The words of the `ssg` command being run (`command_line`); empty for Python callers, whose
# paths keep their slashes and whose process's words are someone else's.
_COMMAND_LINE: ContextVar[tuple[str, ...]] = ContextVar("command_line", default=())


@contextmanager
def command_line(words: Sequence[str]) -> Iterator[None]:
    """While an `ssg` command runs: its words, for `_refuse_slash_on_file`."""
    token = _COMMAND_LINE.set(tuple(words))
    try:
        yield
    finally:
        _COMMAND_LINE.reset(token)


def _refuse_slash_on_file(path: str | Path) -> None:
    """A name ending in `/` asks for a directory, as `cp` reads it; refuse it unless it is one.

    `pathlib` drops the slash (typer hands us `Path("notes.txt")` for `-o notes.txt/`), which
    would write the file `notes.txt`, so the running command's own words are checked too."""
    name = str(path)
    if isinstance(path, Path):
        name = next((a for a in _argv_values() if a.endswith("/") and Path(a) == path), name)
    if name.endswith("/") and name.rstrip("/") and not os.path.isdir(name):
        raise SsgError.single("not a directory", one_line(name))


def _argv_values() -> Iterator[str]:
    """Each word of the command line, and the value of each `--name=VALUE` or `-oVALUE`."""
    for arg in _COMMAND_LINE.get():
        yield arg
        if arg.startswith("--") and "=" in arg:
            yield arg.split("=", 1)[1]
        elif arg.startswith("-") and not arg.startswith("--") and len(arg) > 2:
            yield arg[2:]


def _check_directory_accepts_files(directory: Path, what: str, name: str) -> None:
    """Create and delete a file in `directory`: the one test that also holds for root (who
    passes every permission check) on a read-only file system or a full inode table."""
    if not directory.is_dir():
        raise SsgError.single(
            f"cannot write the {what}: the directory {directory} does not exist", name
        )
    try:
        fd, probe = tempfile.mkstemp(prefix=".ssg-probe.", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise SsgError.single(f"cannot write the {what}: {exc.strerror}", name) from None


def _check_not_an_input(
    out: Output, inputs: Iterable[str | Path], in_place: Iterable[str | Path]
) -> None:
    allowed = [Path(p) for p in in_place]
    for given in map(Path, inputs):
        if not given.exists():
            continue
        if given.is_dir():
            inside = out.target.parent.resolve() == given.resolve()
            if inside and out.target.suffix.lower() == ".json" and not out.stream:
                raise SsgError.single(
                    f"the {out.what} would be written into the input directory {given}, where "
                    "it would be read as a scene; write it elsewhere",
                    str(out.path),
                )
            continue
        if _same_file(out.target, given) and not any(_same_file(given, a) for a in allowed):
            raise SsgError.single(
                f"the {out.what} is the input file {given}; writing it would destroy the "
                "input: write it elsewhere",
                str(out.path),
            )


def _check_distinct(out: Output, others: Iterable[Output]) -> None:
    for other in others:
        same = (out.stdout and other.stdout) or (
            not out.stdout and not other.stdout and _same_file(out.target, other.target)
        )
        if same and not (out.stream and not out.stdout):  # /dev/null twice is fine
            raise SsgError.single(
                f"the {out.what} and the {other.what} are the same file; give two names",
                str(out.path),
            )


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


@contextmanager
def write_output(out: Output, kept: Path | None = None) -> Iterator[TextSink | Any]:
    """A text file to write `out` through: a stream for devices, FIFOs and standard output,
    else an atomic replacement.  A failed write raises `SsgError` naming the output; the
    output is then its old content (or absent).  `kept` is a journal that survives the failure,
    named in the message so the user knows `--resume` finishes the run."""
    note = f"; the journal {kept} is kept: --resume finishes the run" if kept else ""
    if out.stdout:
        yield sys.stdout  # a closed pipe (BrokenPipeError) is the CLI's to end quietly
        sys.stdout.flush()
        return
    try:
        if out.stream:
            with _stream(out.target) as sink:
                yield sink
        else:
            with atomic_writer(out.target) as sink:
                yield sink
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise out.fail(exc, note) from None


def _stdout_descriptor(out: Output) -> int:
    """Standard output's file descriptor, for bytes; a notebook's or a test's captured output
    has none (it failed with "cannot write the picture: None")."""
    try:
        return sys.stdout.fileno()
    except (OSError, ValueError, AttributeError):
        raise SsgError.single(
            f"cannot write the {out.what} to standard output here: it is not a file (a "
            "notebook's or captured output); give a file path",
            out.name,
        ) from None


def write_output_bytes(out: Output, data: bytes) -> None:
    """`write_output` for binary content (pictures): streams written in place, regular files
    replaced atomically, a failed write `SsgError` naming the output."""
    try:
        if out.stdout:
            sys.stdout.flush()
            write_all(_stdout_descriptor(out), data)
        elif out.stream:
            fd = os.open(out.target, os.O_WRONLY | os.O_CLOEXEC)
            try:
                write_all(fd, data)
            finally:
                os.close(fd)
        else:
            write_bytes_atomic(out.target, data)
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise out.fail(exc) from None


def write_output_text(out: Output, text: str, kept: Path | None = None) -> None:
    with write_output(out, kept) as f:
        f.write(text)


@contextmanager
def _stream(path: Path) -> Iterator[TextSink]:
    """A device or FIFO opened as it is: no O_CREAT (never a new regular file in its place), no
    rename, no fsync (a device need not support it)."""
    fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    try:
        sink = TextSink(fd)
        yield sink
        sink.flush()
    finally:
        os.close(fd)


# -------------------------------------------------------------------------- locks ---


@contextmanager
def output_lock(lock: Path, what: str, name: str) -> Iterator[None]:
    """Hold an exclusive `flock` on the file `lock` while the block runs; refuse (SsgError) if
    another process holds it.  The lock file is removed at the end.  A killed holder's lock is
    released by the kernel; its file stays, harmless, and the next run takes it."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise SsgError.single(f"cannot lock the {what}: {exc.strerror}", name) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
                raise SsgError.single(f"cannot lock the {what}: {exc.strerror}", name) from None
            raise SsgError.single(
                f"another ssg run is writing this {what} (it holds the lock {lock}); wait for "
                "it to finish, or write elsewhere",
                name,
            ) from None
        if _still_there(fd, lock):
            break
        os.close(fd)  # the holder removed the file as we opened it: take the new one
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)
        os.close(fd)


def _still_there(fd: int, lock: Path) -> bool:
    try:
        return os.path.samestat(os.fstat(fd), os.stat(lock))
    except FileNotFoundError:
        return False


@contextmanager
def lock_outputs(outputs: Iterable[Output | None]) -> Iterator[None]:
    """Lock every regular-file output (streams need none): `.NAME.lock` beside it."""
    files = [o for o in outputs if o is not None and not o.stream]
    with _locks(files):
        yield


def lock_part(name: str) -> str:
    """The output's name as its lock file `.NAME.lock` holds it: shortened (`fitted_name`)
    when the whole name and the lock's 6 more bytes would not fit in a file name."""
    return fitted_name(name, len("..lock"))


def lock_path(target: Path) -> Path:
    """The lock file `.NAME.lock` beside an output file (`lock_outputs` takes it)."""
    return target.with_name(f".{lock_part(target.name)}.lock")


@contextmanager
def _locks(files: list[Output]) -> Iterator[None]:
    if not files:
        yield
        return
    first = files[0]
    with output_lock(lock_path(first.target), first.what, str(first.path)), _locks(files[1:]):
        yield


# -------------------------------------------------------------- output directories ---


_MADE: list[list[Path]] = []  # directories check_directory made, per `unused_removed` block


def check_directory(path: str | Path, what: str = "output directory") -> Path:
    """A directory to write files into: made if absent; refused if it is a file, a device or
    standard output, or cannot take a new file."""
    path = _usable_name(path, what)
    if str(path) in STDOUT_NAMES:
        raise SsgError.single(f"the {what} must be a directory, not standard output", str(path))
    if path.exists() and not path.is_dir():
        raise SsgError.single(f"the {what} exists and is not a directory", str(path))
    if _MADE:
        _MADE[-1] += [p for p in (path, *path.parents) if not p.exists()]  # nearest first
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SsgError.single(f"cannot create the {what}: {exc.strerror}", str(path)) from None
    _check_directory_accepts_files(path, what, str(path))
    return path


@contextmanager
def unused_removed() -> Iterator[None]:
    """Output directories made during the block are removed again when it fails and leaves
    them empty: a command stopped by a mistake (a bad grammar, no scene found) leaves no
    empty directory behind; one that holds files it wrote stays (they are kept work)."""
    _MADE.append([])
    try:
        yield
    except BaseException as exc:
        if getattr(exc, "exit_code", 1) != 0:  # typer's Exit(0) is a normal end
            for made in _MADE[-1]:
                try:
                    made.rmdir()
                except OSError:
                    pass  # not empty, or not ours any more
        raise
    finally:
        _MADE.pop()


def directory_lock(directory: Path, what: str = "output directory") -> Any:
    """The lock of one writer into `directory` (`.ssg.lock` in it)."""
    return output_lock(directory / ".ssg.lock", what, str(directory))
