"""The daemon's errors, in the project's one exception tree: the configuration's and acquisition's.

Each class also inherits the builtin it resembles: code that only knows
``OSError`` or ``ValueError`` still catches it.  Messages are one line and name
the source.  An unplugged adapter is *not* an exception for callers of
:meth:`~ballbar.daemon.sources.Source.read`: the source turns it into an
``unplugged`` event and retries; :class:`SourceUnplugged` exists for code that
talks to a port directly.
"""

from __future__ import annotations

from ballbar.analysis.errors import BallbarError


class ConfigError(BallbarError, ValueError):
    """A configuration mistake: names the section and key."""


class SourceError(BallbarError, OSError):
    """A sample source failed: the port cannot be opened, read or written."""


class SourceConfigError(BallbarError, ValueError):
    """A source URL or option is invalid (unknown scheme or key, bad value)."""


class SourceUnplugged(SourceError):
    """The port went away mid-read (a USB adapter pulled, a pty closed)."""


class SourceClosed(SourceError):
    """The source was used after :meth:`close`."""


__all__ = ["ConfigError", "SourceClosed", "SourceConfigError", "SourceError", "SourceUnplugged"]
