"""Progress on stderr: a ``tqdm`` bar on a terminal, plain lines in logs.

Used by the command lines (``tofcore render``'s passes here, ``tofcore-batch run``'s frames in
:mod:`batch.run`), never by the simulator itself: ``import tofcore`` and :func:`tofcore.render` do not
import tqdm, so tofcore renders in Blender's Python, which has none.

=====================  =========================================================================
where the output goes  what it shows
=====================  =========================================================================
a terminal, tqdm       one bar redrawn in place (``\\r``), the estimated depth error as postfix
installed
a terminal without     plain lines, as in a log
tqdm
a file or pipe (CI,    plain lines: no carriage returns, no escape codes; a render prints at
``blender -b`` logs)   most one line every :data:`PLAIN_INTERVAL_S` seconds, and its last pass
``quiet``              nothing
=====================  =========================================================================

Before a pass ends, :meth:`PassProgress.activity` (``render(activity=...)``) moves the bar too: while
the compiled tracer's kernels compile (once per install) the bar reads :data:`COMPILE_TEXT` with the
seconds so far, and inside a pass it advances by blocks of pixels; plain lines say the same at most
every :data:`PLAIN_INTERVAL_S` seconds.

tqdm's own environment variables (``TQDM_MININTERVAL``, ``TQDM_DISABLE``, …) apply to the bar.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

#: Least seconds between two plain progress lines of one render (the first and last pass always print).
PLAIN_INTERVAL_S = 5.0

#: What the bar and the log say while the compiled tracer's kernels compile.
COMPILE_TEXT = "compiling the tracer (once per install)"


def tqdm_class():
    """The ``tqdm.tqdm`` class, or None when tqdm is not installed (e.g. in Blender's Python)."""
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm


def is_terminal(stream: TextIO) -> bool:
    """True when ``stream`` is an open terminal (a file, pipe or closed stream is not)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def use_bar(stream: TextIO) -> bool:
    """A redrawn bar on ``stream``: it is a terminal and tqdm is installed."""
    return is_terminal(stream) and tqdm_class() is not None


def format_error_mm(error_m: float | None) -> str:
    """``"3.21 mm"``, or ``"– mm"`` before the first estimate."""
    return f"{error_m * 1000:.2f} mm" if error_m is not None else "– mm"


class PassProgress:
    """The passes of one render; call it with each convergence-log row (``render(progress=...)``).

    Parameters
    ----------
    quiet : print nothing.
    total : the render's most samples per pixel; given, the bar is drawn (at 0, its clock running) as soon
        as the progress starts, before the first pass ends; else at the first pass.
    stream : where to write (default ``sys.stderr``).
    bar : force (True) or refuse (False) the tqdm bar; default: :func:`use_bar` of ``stream``.
    plain_interval_s : least seconds between plain lines (the first and the last pass always print).

    Call :meth:`close` (or use it as a context manager) when the render ends: it finishes the bar's
    line, or prints the last pass if the interval held it back.
    """

    def __init__(self, *, quiet: bool = False, stream: TextIO | None = None, bar: bool | None = None,
                 plain_interval_s: float = PLAIN_INTERVAL_S, total: int | None = None):
        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.bar = (not quiet) and (use_bar(self.stream) if bar is None else bar and tqdm_class() is not None)
        self.plain_interval_s = plain_interval_s
        self._tqdm = None                      # the bar, made at the first pass
        self._last_line = -float("inf")        # perf_counter of the last plain line
        self._pending: dict | None = None      # a row the interval held back
        self._started = time.perf_counter()    # the render's start, for the plain lines inside a pass
        self._compiling = False                # the bar's text is COMPILE_TEXT
        if self.bar and total is not None:
            self._start_bar(total)

    def __call__(self, row: dict) -> None:
        if self.quiet:
            return
        if self.bar:
            self._draw(row)
            return
        now = time.perf_counter()
        last = row["spp"] >= row["spp_max"]
        if row["pass"] == 1 or last or now - self._last_line >= self.plain_interval_s:
            self._line(row)
            self._last_line = now
            self._pending = None
        else:
            self._pending = row

    def activity(self, event: dict) -> None:
        """What a pass does before it ends (``render(activity=...)``): the compile stage, or the samples per
        pixel traced so far."""
        if self.quiet:
            return
        compiling = event.get("stage") == "compile"
        if self.bar:
            if self._tqdm is None:
                self._start_bar(event.get("spp_max", 1))
            if compiling:
                self._tqdm.set_description_str(COMPILE_TEXT, refresh=False)
                self._tqdm.set_postfix_str(f"{event['seconds']:.0f} s", refresh=False)
            else:
                if self._compiling:
                    self._tqdm.set_description_str("render", refresh=False)
                    self._tqdm.set_postfix_str(f"est. error {format_error_mm(None)}", refresh=False)
                self._tqdm.update(max(0, min(int(event["spp"]), event["spp_max"]) - self._tqdm.n))
            self._compiling = compiling
            self._tqdm.refresh()
            return
        now = time.perf_counter()
        if compiling and not self._compiling or now - max(self._last_line, self._started) >= self.plain_interval_s:
            self.stream.write(f"{COMPILE_TEXT}: {event['seconds']:.0f} s\n" if compiling else
                              f"pass {event['pass']}: {event['spp']:.1f}/{event['spp_max']} spp so far  "
                              f"{now - self._started:.1f} s\n")
            self.stream.flush()
            self._last_line = now
        self._compiling = compiling

    def _start_bar(self, total: int) -> None:
        """Draw the bar at 0 now: its clock starts with the render, not at the first pass."""
        self._tqdm = tqdm_class()(total=total, unit="spp", desc="render", file=self.stream, dynamic_ncols=True,
                                  leave=True, mininterval=0)
        self._tqdm.set_postfix_str(f"est. error {format_error_mm(None)}", refresh=True)

    def _draw(self, row: dict) -> None:
        if self._tqdm is None:
            self._start_bar(row["spp_max"])
        if self._compiling:
            self._tqdm.set_description_str("render", refresh=False)
            self._compiling = False
        self._tqdm.set_postfix_str(f"est. error {format_error_mm(row['est_depth_error_m'])}", refresh=False)
        self._tqdm.update(max(0, min(row["spp"], row["spp_max"]) - self._tqdm.n))
        self._tqdm.refresh()    # every pass is drawn, whatever tqdm's rate limits held back

    def _line(self, row: dict) -> None:
        done = min(1.0, row["spp"] / row["spp_max"]) if row["spp_max"] else 1.0
        eta = row["seconds"] / done * (1 - done) if done > 0 else 0.0   # at this pass's seconds per sample
        self.stream.write(f"pass {row['pass']}: {row['spp']}/{row['spp_max']} spp  est. error "
                          f"{format_error_mm(row['est_depth_error_m'])}  {row['seconds']:.1f} s  ETA {eta:.0f} s\n")
        self.stream.flush()

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()
            self._tqdm = None
        elif self._pending is not None:
            self._line(self._pending)
            self._pending = None

    def __enter__(self) -> "PassProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
