"""Child processes that take Ctrl-C as a terminal's foreground job would."""

from __future__ import annotations

import signal


def default_sigint() -> None:
    """`preexec_fn` for a child that must see SIGINT: a test run as a background job of a
    non-interactive shell (or under nohup) ignores SIGINT, and children inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
