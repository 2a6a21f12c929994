"""detcal calibration library: numpy + scipy only."""
