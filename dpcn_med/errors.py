"""Exceptions for a user's mistakes: the CLI turns them into one line and exit code 2."""


class InputError(ValueError):
    """An input (grid, image, file, option) is unusable; the message names it, its value and the fix."""


class InputNotFoundError(InputError, FileNotFoundError):
    """An input path does not exist; a ``FileNotFoundError`` too, so either ``except`` clause catches it."""
