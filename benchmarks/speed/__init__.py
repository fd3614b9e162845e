"""Cost measurements (wall time per call) that compare configurations in one run."""
