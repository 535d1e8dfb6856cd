"""Tracking (pan/tilt/zoom) cameras: a pose and a focal length at every frame.

Every tracking camera is registered at every frame against the *fixed* static model, then its whole
sequence is refined jointly with priors, because per-frame focal and depth trade off (a zoom-in looks
like a dolly-in) and per-frame estimates drift and stutter.

The stage, one module per part (import each name from the module that defines it):

- :mod:`.options`: :class:`~.options.TrackingOptions`, the settings of every part;
- :mod:`.lens`: the lens encoder's focal readings smoothed into the focal prior, and a rig's zoom
  lens table as each frame's distortion, for undistorting its keypoints;
- :mod:`.observe`: the static reference and each camera's 2D-3D and 2D-2D matches;
- :mod:`.solve`: the initial values and the batched torch Levenberg-Marquardt refinement, its
  covariance, and whether a solution is supported;
- :mod:`.calibrate`: the whole stage (:func:`~.calibrate.calibrate_tracking_cameras`): every camera
  observed and initialised, solved from its starts along the zoom/dolly valley, its 2D-3D matches
  found again guided by the solution, and solved once more.

``TrackingOptions.mode="free"`` drops both priors (per-frame focal and centre free, still joint);
``"independent"`` also drops the 2D-2D terms: every frame alone, the classic per-frame registration.
"""
