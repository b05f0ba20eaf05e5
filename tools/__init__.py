"""vislam command line, file outputs and plots."""
