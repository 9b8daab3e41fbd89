"""Interactive web viewer (viser): ``anisdf view RUN`` and ``anisdf train ... --viewer``. Needs the ``viewer`` extra."""

from anisdf.viewer.server import Viewer, check_listen

__all__ = ["Viewer", "check_listen"]
