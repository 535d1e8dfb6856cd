"""Camera calibration: static SfM, tracking-camera refinement, colour calibration, dense points."""
