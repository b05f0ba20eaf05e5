"""One module per ``vislam`` command: ``add_parser(subparsers)`` and ``main(args) -> exit code``."""

from . import batch, check, demo, eval, mc, run, synth, track

COMMANDS = (run, check, eval, track, synth, demo, mc, batch)
