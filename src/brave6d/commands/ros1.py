"""``brave6d ros1 BUNDLE_OR_RELEASE``: :mod:`brave6d.ros_interface.ros1.cli` on the scenes of a bundle or a release
(assembled by :func:`brave6d.commands.scenes.scene_sources`)."""

from brave6d.commands.scenes import serving_run
from brave6d.ros_interface.ros1.cli import configure

__all__ = ["configure", "run"]

run = serving_run("brave6d.ros_interface.ros1.cli")
