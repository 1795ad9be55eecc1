"""Progress bars: drawn on terminals only (a log file gets no carriage-return runs)."""

from __future__ import annotations

import io

from plenocl.io.progress import iteration_bar, pair_bar


def test_bars_write_nothing_when_the_output_is_not_a_terminal(capsys):
    with iteration_bar(5, "mlem") as callback:
        for i in range(1, 6):
            callback(i, 0.5)
    with pair_bar(3) as advance:
        for _ in range(3):
            advance()
    err = capsys.readouterr().err
    assert "\r" not in err and "mlem" not in err and "pairs" not in err


def test_bars_draw_on_a_terminal(monkeypatch, capsys):
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    monkeypatch.setattr("sys.stderr", term)
    with iteration_bar(5, "mlem") as callback:
        callback(5, 0.25)
    assert "mlem" in term.getvalue() and "0.25" in term.getvalue()
