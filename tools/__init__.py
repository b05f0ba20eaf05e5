"""The ``vislam`` command line: ``cli`` (the parser), ``commands`` (one module per command),
``options`` (a command's configuration), ``console`` (messages, progress), ``outputs`` (the files
of a run), ``report`` (summary) and ``plots``."""
