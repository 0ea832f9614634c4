"""Exit codes of the ``ndtom`` command, one set for all its commands (``ndtom_ti.cli``,
``ndtom_ti.viewer.cli``) and for the stop signals of mapping (``ndtom_ti.signals``).

- 0 ``EXIT_OK``: done (closing the viewer with Ctrl-C is the normal way to end ``ndtom view``).
- 1 ``EXIT_FAILURE``: failed: mapping stopped early by the memory budget or a bad scan (what
  was mapped is saved, marked incomplete); the map, a page or a file could not be written
  (a read-only or full file system, found before the work or during the write); an optional
  package a command needs is missing; an internal error.
- 2 ``EXIT_USAGE``: bad input or options (unreadable recording, missing topic or poses, bad
  option or config file, missing or corrupt map file, an output path in a missing folder, a
  folder or device, or one that is an input, a host that cannot be listened on); one
  ``Error:`` line and a ``Hint:``, no traceback.
- 128 + the signal's number: interrupted; 130 (``EXIT_INTERRUPTED``) by Ctrl-C (SIGINT),
  143 (``EXIT_TERMINATED``) by SIGTERM. What was mapped is saved, marked incomplete.
"""

from __future__ import annotations

import signal

__all__ = ["EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_TERMINATED", "EXIT_USAGE", "signal_exit_code"]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


def signal_exit_code(signum: int) -> int:
    """The exit code of a command stopped by signal ``signum``: 128 + its number."""
    return 128 + int(signum)


EXIT_INTERRUPTED = signal_exit_code(signal.SIGINT)  # 130
EXIT_TERMINATED = signal_exit_code(signal.SIGTERM)  # 143
