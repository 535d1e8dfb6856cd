"""Production: what a studio needs around reconstruction (no Prefect here; flows/ drives it).

- :mod:`~volcap_core.production.segments` — split a take into overlapping GPU-sized segments.
- :mod:`~volcap_core.production.presets` — the one table of named quality presets: training
  schedule, segment budget, Face Rig and enhancer sizes (``volcap reconstruct --preset`` and a
  spec's ``quality:``).
- :mod:`~volcap_core.production.performance` — a reconstructed performance: segment models,
  blending across overlaps, rendering at any time.
- :mod:`~volcap_core.production.shot` — shots (camera paths over a performance) from JSON, the
  camera at a frame, cropped RGBA EXR frames with camera metadata.
- :mod:`~volcap_core.production.steps` — the step kinds of a plan, each with its parameters as a
  pydantic model.
- :mod:`~volcap_core.production.spec` — the production spec (YAML) and the planner that decides
  which steps a spec needs.

See ``docs/production-spec.md``, ``docs/shots.md`` and ``docs/operations.md``.
"""
