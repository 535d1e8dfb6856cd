"""Video files (MP4, MOV, M4V, MKV) in, through PyAV (FFmpeg): probe, and decode frame by frame
to non-linear R'G'B' with the signal range and Y'CbCr matrix made explicit.

A video's *frame number* ``n`` is the ``n``-th picture its decoder outputs (presentation order,
after FFmpeg applies the container's edit list), counting from 0; the container's own timecode
track is not read. :func:`probe_video` counts the frames by demuxing (no decoding) and reads the
stream's colour tags; :func:`iter_video_frames` decodes a run of frames, one picture in memory at
a time, and refuses a video that ends before the run does, naming the file and the frame.

Decoding is exact where the standards are: Y'CbCr code values are read from the decoded planes
(8 to 16 bits), the range expanded (limited: ``Y' = (Y - 16·2^(b-8)) / (219·2^(b-8))``,
``Cb, Cr = (C - 128·2^(b-8)) / (224·2^(b-8))``; full: ``Y' = Y / (2^b - 1)``,
``Cb, Cr = (C - 2^(b-1)) / (2^b - 1)``) and the matrix of ITU-R BT.709, BT.601 or BT.2020 (non-
constant luminance) applied. Subsampled chroma (4:2:0, 4:2:2) is upsampled linearly at H.273's
default chroma location (:func:`upsample_chroma`). Values outside ``[0, 1]`` (limited range's foot- and head-room) are kept.
Linearising (the transfer function) and primaries are the caller's: ``volcap_core.ingest``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Literal

import numpy as np

from volcap_core.imageio.errors import ImageReadError

__all__ = [
    "VIDEO_EXTENSIONS",
    "VideoInfo",
    "is_video_path",
    "iter_video_frames",
    "probe_video",
    "upsample_chroma",
    "ycbcr_to_rgb",
]

#: file name endings read as video (case-insensitive)
VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".mkv")

Transfer = Literal["bt709", "srgb", "linear"]
SignalRange = Literal["limited", "full"]
Matrix = Literal["bt709", "bt601", "bt2020"]
Primaries = Literal["bt709", "bt601-625", "bt601-525", "bt2020"]

#: FFmpeg's AVColorTransferCharacteristic → the transfer it means. BT.601 (SMPTE 170M) and
#: BT.2020 (10/12-bit) specify the BT.709 OETF itself.
_TRC_TAGS: dict[int, str] = {1: "bt709", 6: "bt709", 14: "bt709", 15: "bt709", 13: "srgb", 8: "linear"}
#: AVColorSpace (the Y'CbCr matrix)
_MATRIX_TAGS: dict[int, str] = {1: "bt709", 5: "bt601", 6: "bt601", 9: "bt2020"}
#: AVColorPrimaries
_PRIMARIES_TAGS: dict[int, str] = {1: "bt709", 5: "bt601-625", 6: "bt601-525", 7: "bt601-525", 9: "bt2020"}
#: AVColorRange
_RANGE_TAGS: dict[int, str] = {1: "limited", 2: "full"}
_UNSPECIFIED = {0, 2}  # 0 is "reserved" for trc/primaries, "RGB" for the matrix (refused below), 2 "unspecified"

#: (Kr, Kb) of each matrix: ITU-R BT.709-6, BT.601-7, BT.2020-2 (non-constant luminance)
_KR_KB = {"bt709": (0.2126, 0.0722), "bt601": (0.299, 0.114), "bt2020": (0.2627, 0.0593)}

_PIX_FMT_RE = re.compile(r"^yuv(?P<j>j?)4(?P<sub>20|22|44)p(?P<bits>\d+)?(?P<end>le|be)?$")


def is_video_path(path: str) -> bool:
    """Whether a capture path names a video file (by its ending, :data:`VIDEO_EXTENSIONS`)."""
    return path.lower().endswith(VIDEO_EXTENSIONS)


@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe_video` reads of a video's first video stream (no picture decoded).

    ``tag_*``: the stream's colour tags as the names this module uses; None when the stream leaves
    it unspecified; ``"unsupported:<name>"`` when it names something volcap does not decode.
    ``full_range_format``: FFmpeg's ``yuvj*`` formats, which are full range whatever the tag says.
    """

    path: Path
    codec: str
    width: int
    height: int
    frame_count: int
    fps: float
    pix_fmt: str
    bits: int
    sample_aspect_ratio: float
    tag_transfer: str | None
    tag_range: str | None
    tag_matrix: str | None
    tag_primaries: str | None
    full_range_format: bool


def _tag(value: int, table: dict[int, str], name: str) -> str | None:
    """A colour tag as this module names it; None when unspecified; "unsupported:<name>" otherwise."""
    if value in table:
        return table[value]
    if value in _UNSPECIFIED:
        return None
    return f"unsupported:{name}"


def _pix_fmt_bits(path: Path, pix_fmt: str) -> tuple[int, bool]:
    m = _PIX_FMT_RE.match(pix_fmt or "")
    if not m or m["end"] == "be":
        raise ImageReadError(path, f"pixel format {pix_fmt!r} is not decoded (volcap reads planar Y'CbCr "
                                   "4:2:0, 4:2:2 and 4:4:4, 8 to 16 bits little-endian)")
    return int(m["bits"] or 8), bool(m["j"])


def probe_video(path: str | Path) -> VideoInfo:
    """The first video stream's size, frame count (by demuxing every packet), rate, pixel format
    and colour tags. :class:`ImageReadError` naming the file when it cannot be opened or demuxed
    (a truncated MP4 often loses its index and cannot be opened at all)."""
    import av

    path = Path(path)
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise ImageReadError(path, "holds no video stream")
            stream = container.streams.video[0]
            cc = stream.codec_context
            # an edit list's cut packets are demuxed flagged as discard and never decoded
            frames = sum(1 for packet in container.demux(stream) if packet.size and not packet.is_discard)
            rate = stream.average_rate or stream.guessed_rate or Fraction(0)
            sar = stream.sample_aspect_ratio
            info_args = dict(codec=cc.name, width=cc.width, height=cc.height, pix_fmt=cc.pix_fmt or "",
                             fps=float(rate), sample_aspect_ratio=float(sar) if sar else 1.0,
                             trc=int(cc.color_trc), rng=int(cc.color_range), matrix=int(cc.colorspace),
                             primaries=int(cc.color_primaries))
    except ImageReadError:
        raise
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise ImageReadError(path, f"not a readable video ({type(exc).__name__}: {exc})") from exc
    if frames == 0:
        raise ImageReadError(path, "its video stream holds no frames")
    bits, full_format = _pix_fmt_bits(path, info_args["pix_fmt"])
    return VideoInfo(
        path=path, codec=info_args["codec"], width=info_args["width"], height=info_args["height"],
        frame_count=frames, fps=info_args["fps"], pix_fmt=info_args["pix_fmt"], bits=bits,
        sample_aspect_ratio=info_args["sample_aspect_ratio"],
        tag_transfer=_tag(info_args["trc"], _TRC_TAGS, f"transfer characteristics {info_args['trc']} (H.273 code)"),
        tag_range=_tag(info_args["rng"], _RANGE_TAGS, f"range {info_args['rng']} (FFmpeg code)"),
        tag_matrix=_tag(info_args["matrix"], _MATRIX_TAGS, f"matrix coefficients {info_args['matrix']} (H.273 code)"),
        tag_primaries=_tag(info_args["primaries"], _PRIMARIES_TAGS, f"colour primaries {info_args['primaries']} (H.273 code)"),
        full_range_format=full_format)


def _plane_array(plane, dtype: np.dtype) -> np.ndarray:
    """One decoded plane ``[h, w]`` as its integer code values (the line padding dropped)."""
    row = plane.line_size // dtype.itemsize
    return np.frombuffer(plane, dtype).reshape(plane.height, row)[:, :plane.width]


def ycbcr_to_rgb(y: np.ndarray, cb: np.ndarray, cr: np.ndarray, bits: int, signal_range: SignalRange,
                 matrix: Matrix) -> np.ndarray:
    """Y'CbCr code values (``y`` ``[H, W]``, ``cb``/``cr`` ``[H, W]`` already at luma size, any
    integer or float dtype) at ``bits`` per sample → non-linear R'G'B' float32 ``[H, W, 3]``:
    nominal black 0, white 1, values outside kept."""
    scale = float(1 << (bits - 8))
    if signal_range == "limited":
        yn = (y.astype(np.float32) - 16.0 * scale) / (219.0 * scale)
        cbn = (cb.astype(np.float32) - 128.0 * scale) / (224.0 * scale)
        crn = (cr.astype(np.float32) - 128.0 * scale) / (224.0 * scale)
    else:
        top = float((1 << bits) - 1)
        mid = float(1 << (bits - 1))
        yn = y.astype(np.float32) / top
        cbn = (cb.astype(np.float32) - mid) / top
        crn = (cr.astype(np.float32) - mid) / top
    kr, kb = _KR_KB[matrix]
    kg = 1.0 - kr - kb
    r = yn + np.float32(2.0 * (1.0 - kr)) * crn
    b = yn + np.float32(2.0 * (1.0 - kb)) * cbn
    g = (yn - np.float32(kr) * r - np.float32(kb) * b) / np.float32(kg)
    return np.stack([r, g, b], axis=-1).astype(np.float32, copy=False)


def _resample_axis(c: np.ndarray, n_out: int, step: int, cosited: bool, axis: int) -> np.ndarray:
    """Linear interpolation of chroma ``c`` (float32) to ``n_out`` luma samples along ``axis``:
    chroma sample ``j`` sits on luma sample ``step·j`` (``cosited``) or midway between the ``step``
    luma samples it covers; edges repeat."""
    n_in = c.shape[axis]
    x = np.arange(n_out, dtype=np.float64)
    pos = x / step if cosited else (x - (step - 1) / 2.0) / step
    pos = np.clip(pos, 0.0, n_in - 1)
    i0 = np.floor(pos).astype(np.intp)
    i1 = np.minimum(i0 + 1, n_in - 1)
    f = (pos - i0).astype(np.float32)
    shape = [1, 1]
    shape[axis] = n_out
    f = f.reshape(shape)
    return np.take(c, i0, axis=axis) * (1.0 - f) + np.take(c, i1, axis=axis) * f


def upsample_chroma(c: np.ndarray, height: int, width: int) -> np.ndarray:
    """A subsampled chroma plane ``[h, w]`` → float32 ``[height, width]`` by linear interpolation at
    the sample positions of ITU-T H.273's default chroma location (type 0, as MPEG-2, H.264 and
    HEVC assume when a stream says nothing, and BT.709/BT.2020 specify for 4:2:2): horizontally
    co-sited with the even luma columns, vertically midway between the two luma rows. A plane at
    luma size is returned as float32 unchanged."""
    out = c.astype(np.float32)
    if out.shape[1] != width:
        out = _resample_axis(out, width, -(-width // out.shape[1]), True, axis=1)
    if out.shape[0] != height:
        out = _resample_axis(out, height, -(-height // out.shape[0]), False, axis=0)
    return out


def _frame_rgb(frame, info: VideoInfo, signal_range: SignalRange, matrix: Matrix) -> np.ndarray:
    if frame.format.name != info.pix_fmt:
        raise ImageReadError(info.path, f"frame changes pixel format to {frame.format.name} "
                                        f"(the stream is {info.pix_fmt})")
    if getattr(frame, "rotation", 0):
        raise ImageReadError(info.path, f"its frames carry a {frame.rotation} degree display rotation, which "
                                        "volcap does not apply: re-encode the video upright")
    dtype = np.dtype(np.uint8 if info.bits == 8 else "<u2")
    y, cb, cr = (_plane_array(p, dtype) for p in frame.planes[:3])
    h, w = y.shape
    return ycbcr_to_rgb(y, upsample_chroma(cb, h, w), upsample_chroma(cr, h, w), info.bits, signal_range, matrix)


def iter_video_frames(info: VideoInfo, first: int, count: int, *, signal_range: SignalRange,
                      matrix: Matrix) -> Iterator[tuple[int, np.ndarray]]:
    """Frames ``first .. first + count - 1`` of the probed video as ``(frame number, R'G'B'
    float32 [H, W, 3])``, decoded from the start in order (frames before ``first`` are decoded and
    dropped: frame-exact, where seeking lands on key frames), one picture held at a time.

    :class:`ImageReadError` naming the file and the frame when the decoder fails or the video ends
    before frame ``first + count - 1``."""
    import av

    if first < 0 or count < 1:
        raise ValueError(f"frames {first}..{first + count - 1} of {info.path}: not a run of frames")
    n = 0
    try:
        with av.open(str(info.path)) as container:
            stream = container.streams.video[0]
            for frame in container.decode(stream):
                if n >= first:
                    rgb = _frame_rgb(frame, info, signal_range, matrix)
                    if rgb.shape[:2] != (info.height, info.width):
                        raise ImageReadError(info.path, f"frame {n} is {rgb.shape[1]}x{rgb.shape[0]}, the "
                                                        f"stream says {info.width}x{info.height}")
                    yield n, rgb
                n += 1
                if n >= first + count:
                    return
    except ImageReadError:
        raise
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise ImageReadError(info.path, f"frame {n} cannot be decoded ({type(exc).__name__}: {exc})") from exc
    raise ImageReadError(info.path, f"the video ends after {n} frame(s); frame {first + count - 1} is needed "
                                    f"(frames are numbered from 0 in decoding order)")
