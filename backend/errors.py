"""Exception types of vislam.

Every error a user can cause by their input is a :class:`VislamError`; the command line
prints its message as one line and exits with code 2.
"""


class VislamError(Exception):
    """Base class of all errors vislam raises on purpose."""


class InputError(VislamError):
    """A user's file or argument is unusable: names the file, the key and what is wrong."""


class ConfigError(VislamError):
    """A configuration key or value is unknown or invalid."""


class OutputError(VislamError):
    """A path to write to is unusable (not a regular file, not writable, no space): names it."""


class FilterError(VislamError):
    """The estimator cannot go on (e.g. the full state would not fit in memory)."""


class HealthWarning(RuntimeWarning):
    """A run's health message (``estimator.health``: NIS out of its band, P repaired, vision all
    gated), issued through :mod:`warnings` for library callers and kept in ``RunStats.health_messages``;
    the command line shows them itself (on stderr, after the run) and silences only this category."""
