"""The robot cell: from a picture (or target poses) and a folder of parts to a verified robot assembly program.

From Python, :func:`assemble` runs what ``python -m cell.run`` (``image-assembly run``) runs::

    import cell

    result = cell.assemble(parts="scenes/chair/parts", poses="scenes/chair/assembly.json")  # or image="....png"
    print(result.exit_code, " > ".join(result.order))  # 0 and the parts in assembly order
    print(f"{result.program.duration_s:.0f} s robot program, simulated: {result.simulation.success}")

``out="out/chair"`` writes the files of the command (report, pictures, trajectory, program); bad input raises a
:class:`BadInput` subclass (:mod:`cell.errors`) naming the culprit, before anything is planned or written.
"""

from cell.api import AssemblyResult, Failure, assemble
from cell.errors import (
    BadCheckpoint,
    BadInput,
    BadMasses,
    BadOption,
    BadOutput,
    BadParts,
    BadPicture,
    BadPoses,
    BadScene,
    BadTarget,
)

__all__ = ["assemble", "AssemblyResult", "Failure", "BadInput", "BadOption", "BadOutput", "BadScene", "BadParts",
           "BadPicture", "BadCheckpoint", "BadPoses", "BadMasses", "BadTarget"]
