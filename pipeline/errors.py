"""Errors a user can cause and fix: the CLI prints them as one line and exits with code 2."""


class UserError(Exception):
    """A mistake in the command line, the configuration or the input data."""


class DataError(UserError):
    """Input data that cannot be read: a missing, unreadable or malformed file."""
