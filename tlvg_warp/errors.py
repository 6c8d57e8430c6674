"""The two failures the CLI reports in one line: bad user input (exit 2) and a file that could not be written
(disk full, no permission: exit 2 too). Anything else is a bug and keeps its traceback."""


class InputError(ValueError):
    """Bad input (a file, a tensor, a flag). The message names the culprit and the problem in one line."""

    def __init__(self, message: str, path=None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class WriteError(Exception):
    """An output file could not be written (the disk is full, the folder is read-only). Raised by the atomic
    writes, which leave the previous version of the file in place and no temporary file behind."""

    def __init__(self, message: str, path):
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


def one_line(message) -> str:
    """A message as one line: embedded text (torch's, a YAML parser's) may span several."""
    return " ".join(str(message).split())
