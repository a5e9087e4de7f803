"""The one user-facing error: `fhld` and `lane_detector` print it as one line and exit 2.

Raise ConfigError for anything the user gave that cannot be used: a parameter, a config or
parameter file, a checkpoint (model.checkpoint.CheckpointError), a bag (bagio.BagError), a
command-line argument. Its message names the value or file and the problem; nothing else is
printed (no traceback). It is a ValueError, so callers that check values keep working.
"""


class ConfigError(ValueError):
    """A value or file from the user that cannot be used; the message names it."""
