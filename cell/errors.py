"""Exit codes of ``python -m cell.run`` and the exceptions that carry them (one module, imported by every stage,
so that ``python -m cell.run``, which runs as ``__main__``, catches the same classes the stages raise).

Bad input is a :class:`BadInput` (exit 2), raised before any planning and before anything is written; its
subclasses say which input is at fault, so that a caller of :func:`cell.assemble` can tell them apart::

    BadInput
    +-- BadOption       an option's value: seed, planner, units, density, time budget
    +-- BadOutput       the output folder holds something other than an earlier run
    +-- BadScene        the scene file
    +-- BadParts        the parts folder or one of its meshes
    +-- BadPicture      the picture
    +-- BadCheckpoint   the perception weights
    +-- BadPoses        the target poses (their file, or poses given in Python)
    +-- BadMasses       the part masses
    +-- BadTarget       a target assembly the cell cannot build: parts under the floor or through each other,
                        out of the arm's reach, heavier than its payload
"""

from __future__ import annotations

EXIT_OK, EXIT_INTERNAL, EXIT_BAD_INPUT, EXIT_PLANNING, EXIT_SIMULATION = 0, 1, 2, 3, 4
EXIT_DISAGREES = 5  # a run from a picture whose predicted assembly does not match the picture: nothing planned


class BadInput(ValueError):
    """Exit 2: the message names the culprit and the fix; nothing is written."""


class BadOption(BadInput):
    """An option's value (``--seed``, ``--planner``, ``--units``, ``--density``, ``--time-budget``)."""


class BadOutput(BadInput):
    """The output folder exists and holds something other than an earlier run."""


class BadScene(BadInput):
    """A malformed scene file; the message names the file, the table and the key."""


class BadParts(BadInput):
    """The parts folder or one of its meshes; the message names the file."""


class BadPicture(BadInput):
    """The picture of the assembled object; the message names the file and what is wrong with it."""


class BadCheckpoint(BadInput):
    """The perception weights: a missing file or one that holds no perception model."""


class BadPoses(BadInput):
    """The target poses: their file, or poses given in Python that do not match the parts."""


class BadMasses(BadInput):
    """The part masses (``--masses``): their file or JSON text, a part name, a mass."""


class BadTarget(BadInput):
    """A target assembly the cell cannot build (the message names the part and the fix)."""


class StageFailed(Exception):
    """Exit 3 (planning), 4 (simulation check) or 5 (the prediction disagrees with the picture) after a stage ran
    and failed; the report is still written."""

    def __init__(self, exit_code: int, stage: str, message: str, part: str | None = None) -> None:
        super().__init__(message)
        self.exit_code, self.stage, self.part = exit_code, stage, part
