"""One error family for problems a user can fix (bad input, bad options).

Command-line entry points catch `DimslamError` and print its message without a traceback;
anything else is a bug and keeps its traceback.
"""


class DimslamError(Exception):
    """A problem with the user's input or options, with a message that says what to fix."""


class DatasetError(DimslamError):
    """A dataset cannot be read: names the file and what is wrong with it."""


class EvaluationError(DimslamError):
    """Trajectories or meshes cannot be compared (no overlap, too few poses, ...)."""
