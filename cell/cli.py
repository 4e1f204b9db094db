"""``image-assembly``: one command for the package's programs, each subcommand the same as its ``python -m`` form.

    image-assembly run --image scenes/chair/chair.png --parts scenes/chair/parts
    image-assembly sequence scenes/chair
    image-assembly --version

The arguments after the subcommand go to that program unchanged (``image-assembly run --help`` shows its own
help); its exit code is the command's.
"""

from __future__ import annotations

import importlib
import sys

# subcommand -> (its python -m form, the module whose main(argv) runs it, what it does)
COMMANDS = {
    "run": ("cell.run", "cell.run", "picture (or poses) and parts in, a verified robot assembly program out"),
    "batch": ("cell.batch", "cell.batch", "many objects at once on a Dask cluster: summaries and a JUnit report"),
    "sequence": ("planning.sequence", "planning.sequence", "the assembly sequence of an assembly folder"),
    "render": ("cell.render", "cell.render", "render an assembly folder from a random view"),
    "synth": ("perception.synth", "perception.synth.__main__", "write procedural furniture as assembly folders"),
    "dataset": ("perception.dataset", "perception.dataset.__main__", "build a dataset of rendered furniture"),
    "train": ("perception.train", "perception.train.cli", "train the perception network"),
    "evaluate": ("perception.evaluate", "perception.evaluate", "evaluate perception weights"),
}
PACKAGE = "image-assembly"


def version() -> str:
    """The installed package's version (its metadata), or that of the source tree's pyproject.toml."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed_version

    try:
        return installed_version(PACKAGE)
    except PackageNotFoundError:  # run from a source tree that is not installed
        import tomllib
        from pathlib import Path

        with open(Path(__file__).resolve().parent.parent / "pyproject.toml", "rb") as file:
            return tomllib.load(file)["project"]["version"]


def usage() -> str:
    width = max(len(name) for name in COMMANDS)
    lines = [f"usage: {PACKAGE} COMMAND [ARGS...]   ({PACKAGE} COMMAND --help for its options)", "",
             "commands (each the same as python -m MODULE):"]
    lines += [f"  {name.ljust(width)}  {what} (python -m {form})" for name, (form, _, what) in COMMANDS.items()]
    lines += ["", "  --version  print the version and exit"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    if argv[0] == "--version":
        print(f"{PACKAGE} {version()}")
        return 0
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"{PACKAGE}: error: unknown command {command!r}; choose one of {', '.join(COMMANDS)}\n\n{usage()}",
              file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[command][1])
    return module.main(rest) or 0  # argparse's usage errors and --help exit from within, with their codes


if __name__ == "__main__":
    sys.exit(main())
