"""Commands that join several stages, on the top floor beside :mod:`brave6d.cli`.

``brave6d serve``, ``ros1`` and ``ros2`` serve a bundle (the serve stage's format) or every scene
of a release (the dataset stage's format). Deciding which, and asking the release's owner for its
scenes, happens here (:mod:`brave6d.commands.scenes`): the serving stages get the scene sources
and never import the dataset stage. Each command module is the stage's command
(``configure`` from it) with the scene sources handed to its ``run``.
"""
