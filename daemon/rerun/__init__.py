"""The live view in Rerun: polar plots, the verdict, findings and trends for a remote viewer.

One job per module:

``options``     the configuration (:class:`ViewerOptions`, from the daemon's ``[rerun]`` section)
``server``      the serve mode's Rerun server in a supervised child process; the connect mode's prober
``buffers``     the fixed-size buffers of samples and history
``blueprint``   the layout (Rerun blueprints) and the trends' definitions
``geometry``    scene geometry: each sample's angle, the fitted model, display coordinates and scale
``findings``    the words: the verdict and findings of the last complete test
``scene``       what is drawn and how it reaches a viewer (sinks, history, the two polar views, trends)
``listener``    :class:`RerunViewer`, the daemon's listener: samples, results and events in

What the view shows and why is :mod:`.scene`'s docstring; how it stays cheap and never blocks the daemon,
:mod:`.listener`'s.
"""

from __future__ import annotations

from .blueprint import TREND_VIEWS, TRENDS, default_blueprint, trend_ranges
from .findings import findings_markdown, headline
from .geometry import (
    R0,
    ArcTiming,
    model_deviation_um,
    nice_scale_um,
    polar_points,
    provisional_timing,
    result_timing,
    setup_deviation_um,
)
from .listener import RerunViewer
from .options import ViewerConfigError, ViewerOptions, viewer_options
from .server import rerun_binary

__all__ = [
    "R0",
    "TRENDS",
    "TREND_VIEWS",
    "ArcTiming",
    "RerunViewer",
    "ViewerConfigError",
    "ViewerOptions",
    "default_blueprint",
    "findings_markdown",
    "headline",
    "model_deviation_um",
    "nice_scale_um",
    "polar_points",
    "provisional_timing",
    "rerun_binary",
    "result_timing",
    "setup_deviation_um",
    "trend_ranges",
    "viewer_options",
]
