"""A Ctrl-C that a library turns into an error of its own is still an interruption (exit 130),
not an internal error (exit 70).  numpy, interrupted while comparing rows in
`np.unique(axis=0)`, raises "Cannot compare structured arrays unless they have a common
dtype": a resumed `ssg fit` stopped by Ctrl-C exited 70 in a session-35 CI run."""

from __future__ import annotations

import pytest
import typer

from ssgc.cli import app as app_module


def test_an_error_raised_after_a_ctrl_c_is_an_interruption(monkeypatch, capsys):
    monkeypatch.setattr(app_module._CtrlC, "pressed", True)
    with pytest.raises(typer.Exit) as info, app_module._user_errors():
        raise TypeError("Cannot compare structured arrays unless they have a common dtype")
    assert info.value.exit_code == 130
    assert "interrupted" in capsys.readouterr().err


def test_an_error_caused_by_an_interrupt_is_an_interruption(capsys):
    with pytest.raises(typer.Exit) as info, app_module._user_errors():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ValueError("a library's own error") from None  # __context__ is kept
    assert info.value.exit_code == 130


def test_any_other_error_is_still_internal(capsys):
    with pytest.raises(typer.Exit) as info, app_module._user_errors():
        raise TypeError("a bug")
    assert info.value.exit_code == 70
    assert "internal error" in capsys.readouterr().err
