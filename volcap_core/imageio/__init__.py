"""Image files in and out: EXR (all flavours ingest meets), PNG, TIFF and DPX; video files in.

Modules, one concern each, each importing only those above it in this list:

- :mod:`~volcap_core.imageio.errors` — ``ImageReadError`` (every failure to read an image,
  naming the file and the reason) and ``SourceChoiceError``.
- :mod:`~volcap_core.imageio.check` — the EXR structure check: pure Python, run on every EXR before
  any byte reaches a decoder; it also parses the header facts the other modules use.
- :mod:`~volcap_core.imageio.parts` — ``PartHeader``, and the parts and views a file holds:
  which picture a part name and a view name choose (OpenEXR multi-part and multi-view conventions).
- :mod:`~volcap_core.imageio.write` — ``encode_exr`` / ``write_exr`` through the OpenEXR
  bindings.
- :mod:`~volcap_core.imageio.plain_frame` — the one EXR shape ingest stores (a *plain frame*):
  recognised, restamped with a new header without re-encoding, decoded from memory.
- :mod:`~volcap_core.imageio.read` — probing and decoding through OpenImageIO: ``read_footage``,
  ``probe_footage``, ``read_image``, ``decode_exr`` and the native readers.
- :mod:`~volcap_core.imageio.video` — video files through PyAV: ``probe_video`` (size, frame
  count, colour tags) and ``iter_video_frames`` (streaming decode to non-linear R'G'B').

Conventions
-----------
* Pixel arrays are ``[H, W, C]`` (row 0 = top row of the data window), C-contiguous.
* ``read_image`` returns float32 R,G,B(,A): EXR values as stored (scene-linear), integer formats
  normalised to [0, 1] code values (no transfer function: ingest owns colour).
* Parts and views are chosen, never guessed: ``read_footage`` / ``probe_footage`` take a part name
  and/or a view name (OpenEXR's multi-part ``name``/``view`` attributes and multi-view convention:
  ``multiView`` lists the views, default first; channels of the others are prefixed ``<view>.``)
  and refuse a multi-part or multi-view file without a choice, listing what it holds.
  ``read_image`` (by part index, default view) is the low-level reader.
* Header facts ingest must not drop (windows, ``chromaticities``, ``adoptedNeutral``,
  ``pixelAspectRatio``, part names and views) come from the structure check's own header parse
  (:class:`~volcap_core.imageio.parts.PartHeader`): no second read of the file.
* Every EXR written here declares its ``chromaticities`` (volcap's working space by default).
* Every failure to read an image raises :class:`~volcap_core.imageio.errors.ImageReadError` naming
  the file and the reason.

This file only describes the package: import each name from the module that defines it.
"""
