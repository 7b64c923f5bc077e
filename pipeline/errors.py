"""Errors a user can cause and fix (the CLI prints them as one line and exits with code 2), and
the runtime's report of a failing stage."""


class UserError(Exception):
    """A mistake in the command line, the configuration or the input data."""


class DataError(UserError):
    """Input data that cannot be read: a missing, unreadable or malformed file."""


class StageFailure(Exception):
    """A stage raised: names the stage and the frame it was working on."""

    def __init__(self, stage: str, frame: int | None, cause: BaseException) -> None:
        where = f" on frame {frame}" if frame is not None else ""
        super().__init__(f"stage '{stage}' failed{where}: {cause}")
        self.stage, self.frame, self.cause = stage, frame, cause


class OutputError(UserError):
    """A run folder that cannot be written (a full disk, no permission)."""


class MappingProcessFailed(Exception):
    """The mapping process died, hung or failed (the process schedule): not the user's doing; the
    run writes what it has and ends with exit code 1."""
