"""``python -m icefab`` and the ``icefab`` command (pyproject's entry point, :func:`run`)."""

import sys


def run() -> None:
    """Load the command's modules, then run it (:func:`icefab.cli.main`). Ctrl-C while they
    load (numpy, scipy, numba: the first half second) is the one-line interruption too; it
    was a traceback in the middle of an import (hunts')."""
    try:
        from icefab.cli import main
    except BaseException as exc:
        from icefab.errors import interruption

        if interruption(exc) is None:
            raise
        sys.stderr.write("icefab: interrupted\n")
        sys.exit(130)
    sys.exit(main())


if __name__ == "__main__":
    run()
