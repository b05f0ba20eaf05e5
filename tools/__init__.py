"""The ``vislam`` command line: ``cli`` (the parser), ``commands`` (one module per command),
``options`` (a command's configuration), ``console`` (messages, progress, stop signals), ``clock``
(the whole process's time), ``outputs`` (the files of a run), ``report`` (summary), ``plots``,
``viewer`` (the Rerun recording) and ``pool`` (the local process pool or Ray that ``batch`` and
``mc`` run on)."""
