"""Terminal output that any locale can show: :func:`use_safe_output`.

The commands print dashes, ``×``, ``…``, ``µ`` and paths. Under a locale whose
encoding cannot hold them (``LC_ALL=C`` without UTF-8 mode: ASCII; a Latin-1
locale: no ``—``), ``print`` raises ``UnicodeEncodeError`` after the work is
done. With :func:`use_safe_output`, ``sys.stdout`` and ``sys.stderr`` encode
what the terminal's encoding cannot hold through the ``"tofcore-fallback"``
error handler:

* a character of :data:`ASCII_FALLBACK` becomes its ASCII spelling (``—`` → ``-``);
* an undecodable byte of a path (Python keeps it as a lone surrogate
  U+DC80–U+DCFF, PEP 383) is written back as that byte, so the path prints as
  the bytes the user typed;
* anything else becomes ``?``.

Nothing changes where the encoding holds the text (UTF-8 terminals, logs).
:func:`say` prints a command's summary so that a stdout that fails (a full
disk) is one note, not an error of the command.
"""

from __future__ import annotations

import codecs
import os
import sys

ERRORS = "tofcore-fallback"

#: What the commands print beyond ASCII, and how it is spelled in ASCII.
ASCII_FALLBACK = {
    "\u2014": "-", "\u2013": "-", "\u2212": "-", "\u2026": "...", "\u00d7": "x", "\u00b7": "*", "\u2192": "->",
    "\u2190": "<-", "\u2264": "<=", "\u2265": ">=", "\u00b1": "+/-", "\u2248": "~", "\u00b5": "u", "\u03bc": "u",
    "\u00b2": "^2", "\u00b3": "^3", "\u207b": "-", "\u00b9": "^1", "\u00b0": " deg", "\u03c4": "tau",
    "\u03c0": "pi", "\u03c3": "sigma", "\u2070": "^0", "\u2022": "*", "\u2018": "'", "\u2019": "'",
    "\u201c": '"', "\u201d": '"', "\u2588": "#", "\u00a0": " ",
}


def _fallback(error: UnicodeError) -> tuple[str | bytes, int]:
    """The codec error handler: ASCII spellings, surrogate-escaped bytes as themselves, else ``?``."""
    if not isinstance(error, UnicodeEncodeError):
        raise error
    text = error.object[error.start:error.end]
    out: list[str | bytes] = []
    for char in text:
        point = ord(char)
        if 0xDC80 <= point <= 0xDCFF:
            out.append(bytes([point - 0xDC00]))
        else:
            out.append(ASCII_FALLBACK.get(char, "?"))
    if all(isinstance(part, str) for part in out):
        return "".join(out), error.end
    # Bytes replacements are written as they are; spellings are ASCII, which every encoding here holds.
    return b"".join(part if isinstance(part, bytes) else part.encode("ascii") for part in out), error.end


codecs.register_error(ERRORS, _fallback)


def use_safe_output() -> None:
    """Make ``sys.stdout`` and ``sys.stderr`` encode with :data:`ERRORS` (keeping their encoding and buffering).

    Called first thing by the command-line entry points (``tofcore``, ``tofcore-batch``); streams that
    cannot be reconfigured (replaced by a caller, e.g. pytest's capture) are left as they are.
    """
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None and stream.errors != ERRORS:
            try:
                reconfigure(errors=ERRORS)
            except (ValueError, OSError):  # a closed stream
                pass


def say(text: str = "") -> bool:
    """``print(text)`` to stdout, flushed; False when stdout cannot take it (a full disk, a closed pipe).

    The commands print their summary after the work is done and written: a stdout that fails (``>
    /dev/full``) must not be reported as a failed render. On failure, one note goes to stderr, and
    stdout is pointed at the null device so that nothing more (nor Python's flush at exit) fails.
    """
    try:
        print(text, flush=True)
        return True
    except OSError as exc:
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, sys.stdout.fileno())
            os.close(null)
        except (OSError, ValueError):
            pass
        print(f"note: stdout: {exc.strerror or exc}; the rest of this command's summary was not shown "
              f"(its work is not affected)", file=sys.stderr)
        return False


def note_line(message, category, filename, lineno, line=None) -> str:
    """``warnings.formatwarning`` for the commands: one line, ``note: …`` for tofcore's notes about the compiled
    tracer's environment (:class:`tofcore.compiled._target.CompiledWarning`), else ``warning: Category: …``;
    never the source line a warning came from."""
    text = " ".join(str(message).split())
    if category.__name__ == "CompiledWarning":
        return f"note: {text}\n"
    return f"warning: {category.__name__}: {text}\n"
