"""User-facing errors.

Every mistake a user can make (bad YAML, a semantic error in a grammar, a scene the grammar
cannot read) ends up as an `SsgError` holding one or more `Diagnostic`s.  The CLI prints them as
``FILE:LINE:COL: severity: message`` and exits non-zero; nothing else ever reaches the user as a
traceback.
"""

from __future__ import annotations

import unicodedata
from dataclasses import dataclass, field
from typing import Literal

Severity = Literal["error", "warning"]


def one_line(text: str) -> str:
    """`text` with control characters, line breaks, lone surrogates, the bidirectional
    overrides and the non-characters U+FFFE, U+FFFF written as escapes (``\\n``, ``\\x1b``,
    ``\\ud800``, ``\\u202e``).

    Messages quote what users wrote (keys, names, values); a newline or a terminal escape in
    one must not split a diagnostic over several lines or recolour the user's terminal, and a
    lone surrogate cannot be written to a UTF-8 terminal at all.
    """
    if text.isprintable():
        return text
    return "".join(repr(c)[1:-1] if _escaped(c) else c for c in text)


# The bidirectional embeddings, overrides and isolates reorder the text after them on a
# terminal (a name can show as another name); U+FFFE and U+FFFF are not characters, and no XML
# or YAML file may hold them.
_REORDERING_OR_NOT_TEXT = frozenset(
    "\u202a\u202b\u202c\u202d\u202e"  # embeddings and overrides
    "\u2066\u2067\u2068\u2069"  # isolates
    "\ufffe\uffff"
)


def _escaped(c: str) -> bool:
    return c in _REORDERING_OR_NOT_TEXT or unicodedata.category(c) in ("Cc", "Cs", "Zl", "Zp")


@dataclass(frozen=True)
class Diagnostic:
    """One located message, formatted like a compiler's (rustc, mypy)."""

    message: str
    file: str | None = None
    line: int | None = None
    column: int | None = None
    severity: Severity = "error"

    def __str__(self) -> str:
        # a message about no file (a missing package, an option) is the program's own
        where = one_line(self.file) if self.file else "<input>" if self.line is not None else "ssg"
        if self.line is not None:
            where += f":{self.line}"
            if self.column is not None:
                where += f":{self.column}"
        return f"{where}: {self.severity}: {one_line(self.message)}"


@dataclass
class SsgError(Exception):
    """A user mistake: carries diagnostics; never a bug in ssgc."""

    diagnostics: list[Diagnostic] = field(default_factory=list)
    exit_code: int = 1

    def __post_init__(self) -> None:
        # One mistake, one message: a part shared through a YAML alias is checked at each use,
        # and checks that overlap (the compiler's, the meshes') can find the same thing.
        self.diagnostics = list(dict.fromkeys(self.diagnostics))
        super().__init__(str(self))

    @classmethod
    def single(
        cls,
        message: str,
        file: str | None = None,
        line: int | None = None,
        column: int | None = None,
        exit_code: int = 1,
    ) -> SsgError:
        return cls([Diagnostic(message, file, line, column)], exit_code)

    def __str__(self) -> str:
        return "\n".join(str(d) for d in self.diagnostics)

    def __reduce__(self) -> tuple[object, tuple[type[SsgError], dict[str, object]]]:
        """Pickled as its fields: an exception is rebuilt from its `args`, here the message,
        which `__post_init__` then read as a list of diagnostics (one per character)."""
        return _unpickled, (type(self), dict(self.__dict__))


def _unpickled(cls: type[SsgError], state: dict[str, object]) -> SsgError:
    error = cls.__new__(cls)
    error.__dict__.update(state)
    Exception.__init__(error, str(error))
    return error


class GrammarError(SsgError):
    """The grammar file is invalid (syntax, schema or semantics)."""


class SceneError(SsgError):
    """A scene file is invalid or cannot be read with the given grammar."""


class SsgWarning(UserWarning):
    """Something a user should hear about that does not stop the command, said in ssg's words.

    Library code warns with it (`warnings.warn`); the command line prints it as
    ``FILE: warning: message`` about the input it concerns, never as Python's warning text
    (a source path and a line of code)."""
