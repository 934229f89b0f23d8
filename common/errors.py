"""The base of every error the project raises on purpose.

``NeedletrackError``: bad input or a state the code cannot work in, its message naming what and
where (file, line and field; message type and field; node and param). Each package's errors
derive from it and from the builtin they behave as (``ValueError`` for bad input,
``RuntimeError`` for a state), so ``except NeedletrackError`` catches the project's own errors
and nothing else. Imports nothing: every package may use it.
"""


class NeedletrackError(Exception):
    """An error raised on purpose by needletrack; the text names what and where."""
