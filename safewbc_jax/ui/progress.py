"""The progress display of a run, a sweep or a tuning run: a tqdm bar on
stderr with its rate, its ETA and the current *phase* ("compiling", "standing",
"motion", "rolling out", ...) as the bar's postfix.

On a terminal it is an ordinary live tqdm bar (redrawn in place at most every 0.1 s).

Off a terminal (stderr redirected to a file, a CI log, a batch job) tqdm's in-place
redraws would turn into one endless line of carriage returns, or hundreds of lines. There
the bar is not drawn; instead :class:`Progress` writes plain, newline-terminated lines
with the same numbers, spelled out for a log::

    [safewbc] squat 0/1500 steps  0%  ? steps/s  ETA ?  elapsed 00:00  (compiling)
    [safewbc] squat 1/1500 steps  0%  ? steps/s  ETA ?  elapsed 01:02  (standing)
    [safewbc] squat 1001/1500 steps  67%  702 steps/s  ETA 00:00  elapsed 01:04  (motion)
    [safewbc] squat 1500/1500 steps  100%  701 steps/s  ETA 00:00  elapsed 01:05  (done)

one when it starts, one at each change of phase, one when it closes, and in between at
most one every ``log_interval`` seconds (default 30 s; a sweep's chunk of minutes thus
gets one line per chunk). A log gets a handful of lines per run, however fast the steps.

The rate (and the ETA from it) leaves out the *warm-up* phases ("compiling" by default):
once one ends, the rate counts only what came after it, so a minute of compilation does
not make the ETA of a 1 kHz loop a minute long.

``quiet=True`` writes nothing at all.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from tqdm import tqdm

LOG_INTERVAL = 30.0   # s: the most frequent periodic line off a terminal
WARMUP = ("compiling",)


class _Null:
    """Where the (undrawn) tqdm bar of the non-terminal mode writes."""

    def write(self, s):
        return len(s)

    def flush(self):
        pass


TTY_FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_str}{postfix}]"


def format_rate(rate, unit: str) -> str:
    if not rate:
        return f"? {unit}/s"
    digits = 0 if rate >= 100 else 1 if rate >= 10 else 2
    return f"{rate:.{digits}f} {unit}/s"


class _Bar(tqdm):
    """tqdm whose rate, once ``rate_origin`` = (n0, t0) is set, is the mean since then,
    shown as ``{rate_str}`` ("701 steps/s", "0.52 rollouts/s")."""

    rate_origin = None

    def use_clock(self, clock) -> None:
        """Read time from ``clock`` (a function of no arguments, in s)."""
        self._time = clock

    def now(self) -> float:
        return self._time()

    @property
    def format_dict(self):
        d = super().format_dict
        # a terminal of unknown size (a pty with no window size): tqdm reads -1 columns and
        # would trim the bar to nothing; draw a 10-column bar instead
        if (self.ncols or 0) <= 0:
            self.ncols = d["ncols"] = None
        if self.rate_origin is not None:
            n0, t0 = self.rate_origin
            dt = self._time() - t0
            # nothing since the warm-up yet: rate 0, which tqdm shows as '?' (no ETA)
            d["rate"] = (self.n - n0) / dt if self.n > n0 and dt > 0 else 0.0
        rate = d["rate"]
        if rate is None and d["elapsed"]:   # as tqdm.format_meter: the mean so far
            rate = (self.n - self.initial) / d["elapsed"]
        d["rate_eff"] = rate
        d["rate_str"] = format_rate(rate, self.unit)
        return d

    def display(self, msg=None, pos=None):
        if (self.nrows or 0) <= 0:   # unknown size (-1 rows): tqdm would draw nothing
            self.nrows = None
        return super().display(msg, pos)


def is_tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):   # no isatty, or a closed file
        return False


class Progress:
    """A progress bar over ``total`` units with a phase; see the module docstring.

    ``stream``: where it writes (default ``sys.stderr`` at creation); ``tty``: force the
    terminal (True) or log-line (False) mode instead of asking ``stream.isatty()``.
    ``total`` may stay None until :meth:`update_to` gives it. ``clock``: the time source
    in seconds (default ``time.perf_counter``; tests pass a fake one).
    """

    def __init__(self, desc: str, total: int | None = None, unit: str = "its", *,
                 initial: int = 0, phase: str | None = None, quiet: bool = False, stream=None,
                 tty: bool | None = None, log_interval: float = LOG_INTERVAL,
                 warmup: tuple = WARMUP, clock=None):
        self.quiet = quiet
        self.desc = desc
        self.phase = phase
        self.warmup = tuple(warmup)
        self.log_interval = float(log_interval)
        self.lines = 0                 # lines written in the log-line mode
        self._bar: Any = None
        self._closed = False
        self._clock = clock or time.perf_counter
        if quiet:
            return
        self.stream = sys.stderr if stream is None else stream
        self.tty = is_tty(self.stream) if tty is None else bool(tty)
        # tqdm writes "DESC: " on a terminal
        kw = dict(desc=desc.rstrip(": "), total=total, initial=initial, unit=unit, leave=True,
                  postfix=phase, smoothing=0.3)
        if self.tty:
            self._bar = _Bar(file=self.stream, dynamic_ncols=True, mininterval=0.1,
                             bar_format=TTY_FORMAT, delay=1e-9, **kw)
        else:
            # never drawn (mininterval inf): used for its counting and its format
            self._bar = _Bar(file=_Null(), mininterval=float("inf"), **kw)
        # (the tty bar was made with a tiny delay so that it draws nothing before this)
        self._bar.use_clock(self._clock)
        self._bar.start_t = self._bar.last_print_t = self._clock()
        self._bar.delay = 0
        if self.tty:
            if total is not None:   # else drawn once update_to gives the total
                self._bar.refresh()
        else:
            self._last_line = self._clock()
            self._started = False
            if total is not None:
                self._line()

    # --- updates -------------------------------------------------------------------------
    def update(self, n: int = 1, phase: str | None = None) -> None:
        """Advance by ``n`` (and enter ``phase`` when given)."""
        bar = self._bar
        if bar is None:
            return
        if phase is not None and phase != self.phase:
            bar.n += n             # the n belong to the phase that ends: counted, not drawn,
            self.set_phase(phase)  # then shown once in the new phase
            return
        bar.update(n)
        if not self.tty and self._clock() - self._last_line >= self.log_interval:
            self._line()

    def update_to(self, n: int, phase: str | None = None, total: int | None = None) -> None:
        """Set the count to ``n`` (and the total, the phase when given)."""
        bar = self._bar
        if bar is None:
            return
        if total is not None and total != bar.total:
            bar.total = total
            if self.tty:
                bar.refresh()
        if not self.tty and not self._started:
            self._line()       # the first line, deferred until the total is known
        self.update(n - bar.n, phase)

    def set_phase(self, phase: str) -> None:
        """Enter ``phase``: shown at once (a line of its own off a terminal)."""
        if phase == self.phase:
            return
        old, self.phase = self.phase, phase
        bar = self._bar
        if bar is None:
            return
        if old in self.warmup and phase not in self.warmup:
            bar.rate_origin = (bar.n, bar.now())
        bar.set_postfix_str(phase, refresh=self.tty)
        if not self.tty:
            self._line()

    def write(self, msg: str) -> None:
        """A message line that does not break the bar."""
        if self.quiet:
            return
        if self.tty and self._bar is not None and not self._closed:
            self._bar.write(msg, file=self.stream)
        else:
            print(msg, file=self.stream, flush=True)

    def close(self, phase: str | None = None) -> None:
        """Leave the bar (or the last line) in ``phase``, when given."""
        if self._closed:
            return
        self._closed = True
        bar = self._bar
        if bar is None:
            return
        if bar.total is None and bar.n == bar.initial:
            # nothing happened (the run failed before its first step): show nothing
            bar.leave = False
        else:
            if phase is not None and phase != self.phase:
                self.phase = phase
                bar.set_postfix_str(phase, refresh=False)
            if not self.tty:
                self._line()
        bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    # --- the log-line mode ----------------------------------------------------------------
    def format_line(self) -> str:
        """The current state as one line of a log (see the module docstring)."""
        d = self._bar.format_dict
        n, total, rate, unit = d["n"], d["total"], d["rate_eff"], d["unit"]
        parts = [f"{self.desc} {n}/{total} {unit}" if total else f"{self.desc} {n} {unit}"]
        if total:
            parts.append(f"{100 * n / total:.0f}%")
        parts.append(d["rate_str"])
        if total:
            parts.append("ETA " + (tqdm.format_interval(max(total - n, 0) / rate)
                                   if rate else "?"))
        parts.append("elapsed " + tqdm.format_interval(d["elapsed"]))
        if self.phase:
            parts.append(f"({self.phase})")
        return "  ".join(parts)

    def _line(self) -> None:
        self._started = True
        print(self.format_line(), file=self.stream, flush=True)
        self.lines += 1
        self._last_line = self._clock()
