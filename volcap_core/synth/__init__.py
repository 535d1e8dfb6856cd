"""Synthetic captures: our own stage footage, made without the reconstruction code.

An analytic ray caster (numpy) renders a textured set, calibration targets, a colour chart and
animated actors from a rig's cameras, applies a camera/sensor model, and writes a capture folder in
the layout of :mod:`volcap_core.capture` with a ``ground_truth/`` folder beside it. See
``docs/synthetic-capture.md``.
"""

from volcap_core.synth.io import read_exr, read_ply
from volcap_core.synth.synthesize import synthesize_capture, synthesize_face_capture

__all__ = ["synthesize_capture", "synthesize_face_capture", "read_exr", "read_ply"]
