"""Progress display of a fit and of ``vsidgen diagnose``.

:class:`FitProgress` is the estimator's ``progress(iteration, elbo,
grad_norm, elapsed)`` callback. On a terminal it keeps one live line (rich)
with the phase, iteration, ELBO, relative gradient and elapsed time;
otherwise (CI logs, pipes) it writes one summary line per phase. The
estimator restarts its iteration count with each phase and names it
beforehand through :meth:`FitProgress.phase` (its ``str()`` is the label:
``noise start data``, ``deterministic limit, stage 2 of at most 12, std × 0.01`` —
the continuation of one fit towards vanishing process noise, not another
start); iterations that restart without a name are counted as noise starts. :class:`DiagnoseProgress`
prints diagnose's messages and, on a terminal, keeps a live line with the
round, the candidate being refitted and an estimate of the time left in the
round (mean time per finished candidate × candidates left) and, under a time limit, when
the limit ends the round.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TextIO

from .errors import printable_lines


@dataclasses.dataclass
class _Start:
    index: int
    label: str = ""
    iterations: int = 0
    elbo: float = float("nan")
    grad: float = float("nan")
    elapsed: float = 0.0


class FitProgress:
    """Estimator progress callback: live line on a terminal, a line per phase otherwise.

    Args:
        stream: where to write (stderr in the CLI).
        live: force the terminal (True) or log (False) mode; default: ``stream.isatty()``.
    """

    def __init__(self, stream: TextIO, *, live: bool | None = None):
        self.stream = stream
        self.live = stream.isatty() if live is None else bool(live)
        self._start: _Start | None = None
        self._last_it = -1
        self._phase: str | None = None   # announced, not yet iterated
        self._named = False              # the estimator names its phases
        self._console = None
        self._live = None
        if self.live:
            from rich.console import Console
            from rich.live import Live

            self._console = Console(file=stream, highlight=False)
            self._live = Live(console=self._console, auto_refresh=False, transient=False)
            self._live.start()

    def _summary(self, st: _Start) -> str:
        return (f"{st.label or f'noise start {st.index}'}: {st.iterations} iterations, ELBO {st.elbo:.8g}, "
                f"|grad| {st.grad:.3g}, {st.elapsed:.1f} s")

    def phase(self, phase) -> None:
        """The next iterations belong to ``phase`` (``str(phase)`` is its label, e.g. an
        :class:`vsidgen.estimator.FitPhase`)."""
        self._phase = str(phase)
        self._named = True

    def __call__(self, iteration: int, elbo: float, grad_norm: float, elapsed: float) -> None:
        label = self._phase
        new = (self._start is None or iteration < self._last_it
               or (label is not None and label != self._start.label))
        # (a phase announced again, e.g. after a bound release, continues its segment)
        self._phase = None
        if new:
            if self._start is not None and not self.live:
                self.stream.write(self._summary(self._start) + "\n")
                self.stream.flush()
            index = 1 if self._start is None else self._start.index + 1
            if label is None:  # restarted without a name: a noise start of an unnamed sequence
                label = (f"{self._start.label} (restarted)" if self._named and self._start is not None
                         else "")
            self._start = _Start(index, label)
        self._last_it = iteration
        st = self._start
        st.iterations, st.elbo, st.grad, st.elapsed = iteration, elbo, grad_norm, elapsed
        if self._live is not None:
            from rich.text import Text

            line = Text.assemble(
                ("fit ", "bold"), (f"{st.label or f'start {st.index}'}  ", "dim"),
                f"iter {iteration:4d}  ", ("ELBO ", "bold"), f"{elbo: .8e}  ",
                ("|grad| ", "bold"), f"{grad_norm:.2e}  ", (f"{elapsed:7.1f} s", "cyan"))
            self._live.update(line, refresh=True)

    def close(self) -> None:
        """End the live line (kept on screen) or write the last start's summary."""
        if self._live is not None:
            self._live.stop()
            self._live = None
        elif self._start is not None and not self.live:
            self.stream.write(self._summary(self._start) + "\n")
            self.stream.flush()
            self._start = None


class DiagnoseProgress:
    """Diagnose's ``progress(message)`` callback plus a live status line on a terminal.

    ``refitting(round, index, total, key)`` is called before each candidate's
    refit; the time left in the round is the mean time per candidate finished in the
    round so far times the candidates left (unknown before the first one ends). Under a
    time limit the line says when the limit ends the round, every time, next to that
    estimate while the estimate is shorter.
    """

    def __init__(self, stream: TextIO, *, live: bool | None = None):
        self.stream = stream
        self.live = stream.isatty() if live is None else bool(live)
        self._round: int | None = None
        self._t_round = 0.0
        self._index0 = 1
        self._status = None
        if self.live:
            from rich.console import Console

            self._console = Console(file=stream, highlight=False)
            self._status = self._console.status("diagnose: base fit")
            self._status.start()

    def __call__(self, message: str) -> None:
        message = printable_lines(message)     # record and file names from the user's data
        if self._status is not None:
            self._console.print(message, markup=False, highlight=False)
        else:
            self.stream.write(message + "\n")
            self.stream.flush()

    def refitting(self, rnd: int, index: int, total: int, key: str, *,
                  limit_left: float | None = None, n: int = 1, action: str | None = None) -> str:
        """Note the start of refit ``index`` (1-based) of ``total``; returns the status text.
        ``limit_left``: seconds to the round's time limit, which bounds the estimate; ``n``:
        candidates refitted together from ``index`` on (one compilation, ``key`` names them);
        ``action``: what is done instead of "refitting {key}" (e.g. a delay profile)."""
        now = time.perf_counter()
        if self._round != rnd:
            self._round, self._t_round, self._index0 = rnd, now, index
        done = index - self._index0     # candidates finished since the round's first line
        left = total - index + 1
        est = (now - self._t_round) / done * left if done > 0 else None
        parts = []
        if est is None:
            parts.append("time left: after the first refit")
        elif limit_left is None or est <= limit_left:
            parts.append(f"about {est:.0f} s left in this round")
        if limit_left is not None:
            parts.append(f"the time limit ends the round in {max(limit_left, 0.0):.0f} s")
        count = f"{index}/{total}" if n <= 1 else f"{index}–{index + n - 1}/{total}"
        text = f"round {rnd}: {action or f'refitting {key}'} ({count}; {'; '.join(parts)})"
        if self._status is not None:
            self._status.update(text)
        return text

    def close(self) -> None:
        if self._status is not None:
            self._status.stop()
            self._status = None


__all__ = ["DiagnoseProgress", "FitProgress"]
