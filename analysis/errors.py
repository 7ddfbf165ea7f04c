"""One exception tree for the analysis engine.

Each subclass also inherits the builtin it resembles, so callers that only know
``ValueError`` still catch it.  Messages are one line and say what was wrong
and where: the command line prints them as they are.
"""

from __future__ import annotations


class BallbarError(Exception):
    """Root of every error the project raises on purpose."""


class PlanError(BallbarError, ValueError):
    """A test plan, machine configuration or option is invalid."""


class DataError(BallbarError, ValueError):
    """Recorded or streamed samples cannot be analysed (malformed, NaN, empty)."""


class DetectionError(DataError):
    """No test matching the plan was found in the samples."""
