"""Viewer sinks for the pipeline. The default is a no-op that imports nothing heavy.

The live rerun viewer (issue 5) plugs in here, and only this module may import rerun.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from mosaic.pipeline import FrameEvent


class Viewer(Protocol):
    """What the pipeline tells a viewer."""

    def frame(self, event: FrameEvent) -> None:
        """One frame was processed (registered, failed or skipped)."""
        ...

    def finish(self, report: dict[str, Any]) -> None:
        """The run ended; `report` is the final report."""
        ...


class NullViewer:
    """Viewer off: costs nothing."""

    def frame(self, event: FrameEvent) -> None:
        pass

    def finish(self, report: dict[str, Any]) -> None:
        pass
