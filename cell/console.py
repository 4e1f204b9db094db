"""What a run says while it works: the stage lines, progress bars and notes on stderr, and each stage's time.

``quiet`` keeps only notices (a failure, a note on the inputs, the perception hint); ``silent`` (the default of
:func:`cell.assemble`) keeps nothing: the caller reads the result instead.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

STAGES = ("perception", "repair", "sequence", "kitting", "motion", "timing", "simulation", "export")


@dataclass
class Console:
    quiet: bool = False
    stage_seconds: dict[str, float] = field(default_factory=dict)
    silent: bool = False

    def say(self, text: str) -> None:
        """Progress: hidden when quiet."""
        if not self.quiet and not self.silent:
            print(text, file=sys.stderr, flush=True)

    def notice(self, text: str) -> None:
        """What the user must see even when quiet: a failure, a note on the inputs."""
        if not self.silent:
            print(text, file=sys.stderr, flush=True)

    @contextmanager
    def stage(self, name: str, detail: str = ""):
        index = STAGES.index(name) + 1
        self.say(f"[{index}/{len(STAGES)}] {name}{': ' + detail if detail else ''}")
        started = time.perf_counter()
        try:
            yield
        finally:
            self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - started

    def bar(self, total: int, unit: str):
        from tqdm import tqdm

        return tqdm(total=total, unit=unit, disable=self.quiet or self.silent, file=sys.stderr, leave=False,
                    dynamic_ncols=True)
