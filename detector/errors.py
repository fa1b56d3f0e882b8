"""Errors raised for user mistakes (bad parameters, bad files). The CLI prints them as one line."""

from __future__ import annotations


class DetectorError(ValueError):
    """A user-facing error: names the culprit (file and/or key) and what was expected.

    Parameters
    ----------
    message : str
        What went wrong.
    key : str, optional
        Dotted key of the offending parameter (``detector.gain_e_per_adu``, ``effects.prnu.sigma``).
    expected : str, optional
        What would have been accepted.
    file : str, optional
        The file the value came from.
    """

    def __init__(self, message: str, *, key: str | None = None, expected: str | None = None,
                 file: str | None = None):
        self.message, self.key, self.expected, self.file = message, key, expected, file
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = []
        if self.file:
            parts.append(str(self.file))
        if self.key:
            parts.append(f"key '{self.key}'")
        head = ": ".join(parts)
        text = f"{head}: {self.message}" if head else self.message
        if self.expected:
            text += f" (expected {self.expected})"
        return text
