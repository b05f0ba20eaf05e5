"""Evaluation: trajectory errors against ground truth (``metrics``, with evo) and the filter's
consistency over Monte Carlo runs (``consistency``)."""
