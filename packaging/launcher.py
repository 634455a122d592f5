"""Entry point of the frozen application (PyInstaller): the ``elastoid`` command.

Without arguments it opens the desktop window; ``elastoid --selftest`` (or
``elastoid selftest``) checks the installation; every other subcommand of the
command line works as in a source install (see docs/cli.md).
"""

import multiprocessing
import sys


def _main() -> int:
    from app.cli import main

    return main()


if __name__ == "__main__":
    # First thing: the mesher runs fTetWild in a *spawned* child process, and a frozen
    # app spawns by re-running this executable with multiprocessing's arguments.
    # freeze_support() recognises them, runs the child's work and exits, before
    # anything parses the command line. (It also serves multiprocessing's resource tracker.)
    multiprocessing.freeze_support()
    sys.exit(_main())
