"""One exception type for bad user input; the CLI turns it into a one-line message and exit code 2."""


class InputError(ValueError):
    """Bad input (a file, a tensor, a flag). The message names the culprit and the problem in one line."""

    def __init__(self, message: str, path=None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)
