"""The calibration benchmark's parts (issue 49): clips as a lab records them, scores on held-out
motions, the summary. Run by ``benchmarks/calibrate_rods.py``."""
