"""Exit codes of ``python -m cell.run`` and the exceptions that carry them (one module, imported by every stage,
so that ``python -m cell.run``, which runs as ``__main__``, catches the same classes the stages raise)."""

from __future__ import annotations

EXIT_OK, EXIT_INTERNAL, EXIT_BAD_INPUT, EXIT_PLANNING, EXIT_SIMULATION = 0, 1, 2, 3, 4
EXIT_DISAGREES = 5  # a run from a picture whose predicted assembly does not match the picture: nothing planned


class BadInput(Exception):
    """Exit 2: the message names the culprit; nothing is written."""


class StageFailed(Exception):
    """Exit 3 (planning), 4 (simulation check) or 5 (the prediction disagrees with the picture) after a stage ran
    and failed; the report is still written."""

    def __init__(self, exit_code: int, stage: str, message: str, part: str | None = None) -> None:
        super().__init__(message)
        self.exit_code, self.stage, self.part = exit_code, stage, part
