"""Errors meant for the user: the CLI prints them as one line and exits with status 2."""


class CliError(Exception):
    """A user-facing error whose message names the problem."""
