"""One module per ``vislam`` command: ``add_parser(subparsers)`` and ``main(args) -> exit code``."""

from . import check, demo, eval, mc, run, synth, track

COMMANDS = (run, check, eval, track, synth, demo, mc)
