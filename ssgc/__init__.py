"""ssgc: the spatial scene grammar compiler.

The Python API (docs/api.md, `ssgc.api`)::

    import ssgc
    g = ssgc.load_grammar("grammars/sink.yaml")
    scenes = g.sample(10, seed=0)
    result = ssgc.parse(g, scenes[0], top=3)
    why = ssgc.explain(g, scenes[0])
    fitted = ssgc.fit(g, scenes, iterations=5)

`import ssgc` loads nothing else: each name is imported when first used, so a script that
only reads the version, and the `ssg` command's start, stay fast.

`ssgc.parse`, `ssgc.fit` and `ssgc.explain` are also the names of the library's own modules
(the parser, the fitter, the explainer).  A name can be only one object, so those three
modules are made callable: `ssgc.parse(grammar, scene)` calls `ssgc.api.parse`, while
`ssgc.parse.parser` is still the parser's module.  Type checkers see the modules; typed code
imports the functions from `ssgc.api`.
"""

from __future__ import annotations

import sys
from types import ModuleType
from typing import Any

__version__ = "0.1.0"

_API = ("load_grammar", "load_scenes", "Grammar", "Scene", "Tree", "Parse", "ParseResult")
_CALLABLE_MODULES = ("parse", "fit", "explain")  # a module of ssgc, and an API function
_MODULES = ("api", "errors")  # named by docs/api.md as `ssgc.api.X`, `ssgc.errors.X`
# `from ssgc import *`: the API (a star import reads each name, so they load then)
__all__ = [*_API, *_CALLABLE_MODULES]


def __getattr__(name: str) -> Any:
    """The API's names, imported on first use (PEP 562)."""
    if name in _API or name in _CALLABLE_MODULES or name in _MODULES:
        import importlib

        if name in _CALLABLE_MODULES or name in _MODULES:
            return importlib.import_module(f"ssgc.{name}")  # bound (and made callable) below
        return getattr(importlib.import_module("ssgc.api"), name)
    raise AttributeError(f"module 'ssgc' has no attribute '{name}'")


def __dir__() -> list[str]:
    return sorted({*globals(), *_API, *_CALLABLE_MODULES, *_MODULES})


class _CallableModule(ModuleType):
    """A module of ssgc that is also the API function of its name (`ssgc.api.NAME`)."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._function()(*args, **kwargs)

    @property
    def __signature__(self) -> Any:
        """The API function's, for `help()`, `inspect.signature` and a notebook's `?`."""
        import inspect

        return inspect.signature(self._function())

    def _function(self) -> Any:
        from ssgc import api

        return getattr(api, self.__name__.rpartition(".")[2])


class _Package(ModuleType):
    """The `ssgc` package: when the import system binds one of the callable modules as its
    attribute (however it was first imported), that module becomes callable."""

    def __setattr__(self, name: str, value: Any) -> None:
        if (
            name in _CALLABLE_MODULES
            and isinstance(value, ModuleType)
            and value.__name__ == f"ssgc.{name}"
        ):
            value.__class__ = _CallableModule
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
