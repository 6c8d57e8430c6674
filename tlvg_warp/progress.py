"""One progress line for a whole run of several phases, with the run's ETA across them.

    p = Progress([("pre", 45, "Fit"), ("stylize", 210, "Stylize"), ("post", 45, "Fit")])
    p.start_phase(0, 0); p.update(1); ...; p.postfix({"loss": "0.0769"}); ...; p.end_phase(); p.close()

On a terminal the line is rewritten in place (a carriage return, cut to the terminal's width). Anywhere else (a
file, a pipe, a CI log) it is plain lines: one at each tenth of the run, at the end of each phase and at least every
``every_s`` seconds, at the log points (``postfix``) so each carries the latest loss; never a carriage return.

The ETA adds, over every remaining step of every phase, that phase's seconds per step: measured in this process
for the phases run so far, for a phase not yet begun the rate of an earlier phase of the same kind (pre and post
are both photometric fits), else the current rate, and then the ETA is a lower bound, shown as ">".
"""
from __future__ import annotations

import shutil
import sys
import time

BAR = 20  # characters of the bar (terminal only)
MILESTONES = 10  # plain lines: one at each tenth of the run


def clock_text(s: float) -> str:
    s = max(0, int(round(s)))
    h, m = divmod(s, 3600)
    m, s = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """``phases``: [(label, steps, kind)] in run order; ``done``: global steps already done (a resumed run)."""

    def __init__(self, phases, done: int = 0, *, stream=None, tty: bool | None = None, every_s: float = 30.0,
                 clock=time.perf_counter, min_interval: float = 0.1):
        self.phases = [(str(a), int(b), str(c)) for a, b, c in phases]
        self.total = sum(n for _, n, _ in self.phases)
        self.stream = stream if stream is not None else sys.stderr
        if tty is None:
            try:
                tty = bool(self.stream.isatty())
            except (AttributeError, ValueError):
                tty = False
        self.tty, self.every_s, self.clock, self.min_interval = tty, float(every_s), clock, float(min_interval)
        self.step = int(done)
        self.t_start = clock()
        self.spent = {}  # phase index -> (steps timed, seconds) in this process
        self.cur = None  # index of the current phase
        self.t_last = None  # time of the last update (or of the phase's start)
        self.fields = {}
        self.drawn = 0.0  # when the terminal line was last drawn
        self.printed_at = clock()  # when the last plain line was written
        self.milestone = self._milestone(self.step)
        self.open_line = False  # a terminal line without its newline yet
        self.printed_at_step = None  # the step of the last plain line

    # --- the estimate -------------------------------------------------------------------------------------------
    def _sec_per_step(self, i: int):
        n, s = self.spent.get(i, (0, 0.0))
        return s / n if n else None

    def eta(self) -> tuple[float | None, bool]:
        """(seconds left, exact): None before any step is timed; exact False when a phase still to come has no
        rate of its kind yet (the estimate then uses the current rate and is a lower bound)."""
        cur = self._sec_per_step(self.cur) if self.cur is not None else None
        if cur is None:
            cur = next((r for r in (self._sec_per_step(i) for i in sorted(self.spent, reverse=True)) if r), None)
        if cur is None:
            return None, False
        left, exact, start = 0.0, True, 0
        for i, (_, n, kind) in enumerate(self.phases):
            remaining = max(0, min(n, start + n - self.step))
            start += n
            if remaining == 0:
                continue
            r = self._sec_per_step(i)
            if r is None:
                same = [self._sec_per_step(j) for j in range(i) if self.phases[j][2] == kind]
                same = [x for x in same if x is not None]
                if same:
                    r = same[-1]
                else:
                    r, exact = cur, False
            left += remaining * r
        return left, exact

    # --- events -------------------------------------------------------------------------------------------------
    def start_phase(self, index: int, k: int = 0) -> None:
        self.cur = index
        self.t_last = self.clock()
        self._draw(force=True)

    def update(self, step: int) -> None:
        """Step ``step`` (global, 1-based) is done."""
        now = self.clock()
        if self.cur is not None and self.t_last is not None:
            n, s = self.spent.get(self.cur, (0, 0.0))
            self.spent[self.cur] = (n + (step - self.step), s + (now - self.t_last))
        self.t_last, self.step = now, step
        self._draw()

    def postfix(self, fields: dict) -> None:
        """The latest values worth showing (loss, Gaussian count, ...), at a log point: a plain line is due when a
        tenth of the run was passed, the phase ended or ``every_s`` went by since the last one."""
        self.fields = dict(fields)
        if self.tty:
            self._draw(force=True)
            return
        m = self._milestone(self.step)
        now = self.clock()
        if m > self.milestone or self._phase_end() or now - self.printed_at >= self.every_s:
            self._print_line()

    def end_phase(self) -> None:
        if not self.tty and self.cur is not None and self._phase_end() and self.step > self._phase_start(self.cur):
            if self.printed_at_step != self.step:
                self._print_line()
        self.cur = None

    def close(self) -> None:
        if self.tty and self.open_line:
            self._draw(force=True)
            self.stream.write("\n")
            self.stream.flush()
            self.open_line = False

    # --- drawing ------------------------------------------------------------------------------------------------
    def _milestone(self, step: int) -> int:
        return step * MILESTONES // max(1, self.total)

    def _phase_start(self, i: int) -> int:
        return sum(n for _, n, _ in self.phases[:i])

    def _phase_end(self) -> bool:
        return self.cur is not None and self.step >= self._phase_start(self.cur) + self.phases[self.cur][1]

    def line(self, bar: bool = False) -> str:
        """The progress text: overall percent and steps, the phase, its rate, elapsed, the run's ETA, the fields."""
        pct = 100.0 * self.step / max(1, self.total)
        parts = []
        head = f"{pct:3.0f}%"
        if bar:
            fill = int(BAR * self.step / max(1, self.total))
            head += " |" + "█" * fill + " " * (BAR - fill) + "|"
        parts.append(f"{head} {self.step}/{self.total}")
        if self.cur is not None:
            label, n, _ = self.phases[self.cur]
            parts.append(f"{label} {min(n, max(0, self.step - self._phase_start(self.cur)))}/{n}")
            r = self._sec_per_step(self.cur)
            if r:
                parts.append(f"{1 / r:.2f} it/s" if r < 1 else f"{r:.2f} s/it")
        parts.append(f"elapsed {clock_text(self.clock() - self.t_start)}")
        left, exact = self.eta()
        parts.append("ETA " + ("?" if left is None else ("" if exact else ">") + clock_text(left)))
        if self.fields:
            parts.append(" ".join(f"{k}={v}" for k, v in self.fields.items()))
        return " | ".join(parts)

    def _draw(self, force: bool = False) -> None:
        if not self.tty:
            return
        now = self.clock()
        if not force and now - self.drawn < self.min_interval:
            return
        self.drawn = now
        width = shutil.get_terminal_size((100, 20)).columns - 1
        self.stream.write("\r" + self.line(bar=True)[:width].ljust(width))
        self.stream.flush()
        self.open_line = True

    def _print_line(self) -> None:
        self.stream.write(self.line() + "\n")
        self.stream.flush()
        self.printed_at, self.printed_at_step = self.clock(), self.step
        self.milestone = self._milestone(self.step)


__all__ = ["Progress", "clock_text"]
