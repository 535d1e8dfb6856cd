"""Atomic writers (and small readers) for what the synthetic capture puts on disk: half-float EXR
frames, canonical-ish JSON, binary PLY point scans. Every writer encodes to bytes and hands them to
:func:`volcap_core.files.write_atomic`."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import OpenEXR

from volcap_core.chromaticities import WORKING_CHROMATICITIES
from volcap_core.files import write_atomic


def write_exr(path: Path, image: np.ndarray, half: bool = True) -> None:
    """(H, W, 3) -> R, G, B channels (linear Rec.709/D65, declared in ``chromaticities``); (H, W) -> one
    channel ``Z``. ZIP-compressed, scanline. Written atomically (temporary file in the same folder, fsync, rename)."""
    arr = np.asarray(image, np.float16 if half else np.float32)
    if arr.ndim == 3:
        channels = {c: np.ascontiguousarray(arr[..., i]) for i, c in enumerate("RGB")}
    else:
        channels = {"Z": np.ascontiguousarray(arr)}
    # the working space's primaries, as every EXR volcap writes declares them (ingest reads them)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "chromaticities": tuple(WORKING_CHROMATICITIES)}
    # The bindings encode to a stream exactly the bytes they would write to a file name.
    out = io.BytesIO()
    with OpenEXR.File(header, channels) as f:
        f.write(out)
    write_atomic(path, out.getvalue())


def read_exr(path: Path) -> np.ndarray:
    """R, G, B (or Z) channels of a single-part EXR as float32 (H, W, 3) or (H, W)."""
    with OpenEXR.File(str(path)) as f:
        if not f.parts:
            raise ValueError(f"{path}: no parts (damaged EXR?)")
        ch = f.channels()
        if "Z" in ch and "R" not in ch:
            return np.asarray(ch["Z"].pixels, np.float32)
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, np.float32)
        return np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"], -1)


def write_json(path: Path, data) -> None:
    write_atomic(path, (json.dumps(data, indent=1, sort_keys=False) + "\n").encode())


def write_ply(path: Path, points: np.ndarray, normals: np.ndarray, comment: str = "") -> None:
    """Binary little-endian PLY with float32 x y z nx ny nz per vertex."""
    pts = np.asarray(points, np.float32)
    nrm = np.asarray(normals, np.float32)
    data = np.concatenate([pts, nrm], axis=1).astype("<f4")
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append(f"comment {comment}")
    header += [f"element vertex {len(pts)}"]
    header += [f"property float {n}" for n in ("x", "y", "z", "nx", "ny", "nz")]
    header += ["end_header"]
    write_atomic(path, ("\n".join(header) + "\n").encode("ascii") + data.tobytes())


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read what :func:`write_ply` writes: points (N, 3) and normals (N, 3), float32."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    if header[0] != "ply" or header[1] != "format binary_little_endian 1.0":
        raise ValueError(f"{path}: not a binary little-endian PLY")
    n = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    props = [line.split()[2] for line in header if line.startswith("property float")]
    data = np.frombuffer(raw, "<f4", count=n * len(props), offset=end).reshape(n, len(props))
    ix = {p: i for i, p in enumerate(props)}
    pts = data[:, [ix["x"], ix["y"], ix["z"]]].astype(np.float32)
    nrm = data[:, [ix["nx"], ix["ny"], ix["nz"]]].astype(np.float32)
    return pts, nrm
