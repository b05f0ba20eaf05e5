"""vislam synthetic scenes with ground truth (see issue 3; not built yet)."""
