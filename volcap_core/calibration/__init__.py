"""Camera calibration of a capture: static wide cameras once (pycolmap + lidar), tracking cameras
at every frame (torch, with encoder-focal and centre priors), plus colour calibration between rigs,
dense per-frame points and COLMAP export. Pure functions; see ``docs/calibration.md``."""
