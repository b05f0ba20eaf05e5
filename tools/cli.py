"""The ``vislam`` command line: one parser, one module per command (``tools.commands``).

Every user error is one line on stderr and exit code 2; Ctrl-C exits 130 and leaves no half file.
"""

from __future__ import annotations

import argparse
import sys

from .. import __version__
from ..backend.errors import VislamError
from .commands import COMMANDS

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vislam", description="Stereo visual-inertial EKF SLAM on SE(3).")
    parser.add_argument("--version", action="version", version=f"vislam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except VislamError as exc:
        print(f"vislam: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("vislam: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
