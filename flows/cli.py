"""The ``volcap`` command.

Exit codes: 0 success; 1 the work failed (stderr is exactly one line saying why: file, camera,
frame, ref or digest; no traceback unless ``--verbose``: flows/cli_output.py); 2 bad usage;
130 / 143 cancelled by SIGINT / SIGTERM (one ``volcap: error: cancelled: …`` line:
flows/cancellation.py). Commands that produce artifacts take ``--json`` and then print their output
references as one JSON object on the last line of stdout. Every flow run ends with a one-line
summary (tasks run / cached / failed, wall time); the same counts are in the ``--json`` object.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from flows.runtime import RunSummary, quiet_prefect_defaults, reproducible_cpu_defaults
from flows.runtime import skip_final_collection, start_api_early  # docs/benchmarks.md, cached reruns

quiet_prefect_defaults(log_level="INFO")
skip_final_collection()  # registered first: the command's exit does not wait on a full collection

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="volcap: 4D volumetric capture, from camera files to Gaussian-splat performances.")
store_app = typer.Typer(no_args_is_help=True, help="Inspect and maintain a content-addressed artifact store.")
app.add_typer(store_app, name="store")

StoreOpt = Annotated[str, typer.Option("--store", envvar="VOLCAP_STORE",
                                       help="store URL: a path, file://, memory:// or s3://bucket/prefix")]
JsonOpt = Annotated[bool, typer.Option("--json", help="print output references as JSON on the last line")]
DEFAULT_STORE = "./.volcap/store"


from flows.cli_output import OUTPUT, CommandError  # noqa: E402 - stdout/stderr contract, --verbose
from flows.cancellation import CANCEL  # noqa: E402 - SIGINT/SIGTERM: exit 130/143 and one line


@app.callback()
def _global_options(verbose: Annotated[bool, typer.Option(
        "--verbose", envvar="VOLCAP_VERBOSE",
        help="DEBUG logs, native libraries' stderr and a failure's traceback (also accepted after the command)")] = False) -> None:
    """volcap: 4D volumetric capture, from camera files to Gaussian-splat performances."""
    # main() reads --verbose (anywhere on the line) before the command runs; declared here for --help.


def _store_url(url: str) -> str:
    from volcap_core.store import normalize_store_url
    return normalize_store_url(url)


def _emit(obj: dict[str, Any], as_json: bool, human: str | None = None) -> None:
    if not CANCEL.finished():  # a SIGINT/SIGTERM is ending the command: no result line
        CANCEL.wait_if_cancelling()
    if human:
        typer.echo(human)
    if as_json:
        typer.echo(json.dumps(obj, sort_keys=True, default=str))


def _progress(label: str):
    """A small stderr progress callback ``(done, total)`` for long local work."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    progress = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        transient=True, console=_stderr_console())
    task_id = progress.add_task(label, total=None)

    def update(done: int, total: int) -> None:
        progress.update(task_id, completed=done, total=total)

    return progress, update


def _stderr_console():
    from rich.console import Console
    return Console(stderr=True)


def _run(flow: Any, **params: Any) -> RunSummary:
    from flows.runtime import run_flow
    OUTPUT.route_logging()  # Prefect's console logs to stdout; an expected failure's traceback to DEBUG
    try:
        summary = run_flow(flow, on_running=CANCEL.flow_run_started, **params)
    except Exception as exc:
        summary = getattr(exc, "run_summary", None)
        if summary is not None:
            typer.echo(summary.line())  # stdout: what ran; main() prints the cause on stderr
        raise
    typer.echo(summary.line())
    return summary


# ---------------------------------------------------------------------------------------------
# synth / ingest / demo
# ---------------------------------------------------------------------------------------------


@app.command()
def synth(out_dir: Annotated[Path, typer.Argument(help="folder to write the capture into")],
          rig: Annotated[str, typer.Option(help="built-in rig name or rig JSON file")] = "demo_scene",
          seed: Annotated[int, typer.Option(help="random seed (same seed, same bytes)")] = 0,
          frames: Annotated[int, typer.Option(min=1, help="frames in the take")] = 24,
          depth: Annotated[bool, typer.Option("--depth/--no-depth", help="also write ground-truth depth maps")] = False,
          lidar: Annotated[bool, typer.Option("--lidar/--no-lidar", help="give the capture its lidar scan (--no-lidar: none, as a studio without a scanner; scene rigs)")] = True,
          static_only: Annotated[bool, typer.Option("--static-only", help="render the rig's static cameras only (no tracking cameras)")] = False,
          actor_of: Annotated[Optional[str], typer.Option("--actor-of", metavar="SCENE_CAPTURE_DIR:N", help="face rigs: film actor N of that synthetic Scene Rig capture (same person, own expressions)")] = None,
          plates: Annotated[bool, typer.Option("--plates", help="scene rigs: also write each static camera's clean plate, plates/<camera>.exr (the empty set through its sensor), for volcap masks --plates")] = False,
          json_out: JsonOpt = False) -> None:
    """Render a synthetic capture (scene or face rig) in the layout ingest reads."""
    from hardware.rig import load_rig
    from volcap_core import synth as synthetic

    t0 = time.perf_counter()
    the_rig = load_rig(rig)
    kind = the_rig.kind
    extra: dict = {}
    if static_only:
        extra["cameras"] = [c.id for c in the_rig.cameras if not c.role.tracks]
    if not lidar:
        if kind == "face":
            raise CommandError("--no-lidar is for scene rigs (the face synthesizer always writes its scan)")
        extra["lidar"] = False
    if actor_of is not None:
        if kind != "face":
            raise CommandError(f"--actor-of is for face rigs (rig {the_rig.name} is a {kind} rig)")
        folder, _, index = actor_of.rpartition(":")
        if not folder or not index.isdigit():
            raise CommandError(f"--actor-of {actor_of!r}: expected SCENE_CAPTURE_DIR:N (N an actor index, 0, 1, ...)")
        extra["actor_of"] = (Path(folder), int(index))
    if plates:
        if kind == "face":
            raise CommandError("--plates is for scene rigs (a Face Rig capture has no static cameras' plates)")
        extra["plates"] = True
    progress, update = _progress(f"rendering {rig}")
    with progress:
        fn = synthetic.synthesize_face_capture if kind == "face" else synthetic.synthesize_capture
        path = fn(out_dir, rig=rig, seed=seed, frames=frames, progress=update, write_depth=depth, **extra)
    wall = time.perf_counter() - t0
    _emit({"capture_dir": str(Path(path).parent), "capture_json": str(path), "wall_s": round(wall, 3)},
          json_out, f"wrote {path} in {wall:.1f} s")


@app.command()
def masks(capture_dir: Annotated[Path, typer.Argument(help="capture folder holding capture.json")],
          plates: Annotated[Optional[Path], typer.Option(help="folder of background plates, <camera id>.exr|png|tif|tiff|dpx in the camera's encoding; a static camera without one gets the median of its take")] = None,
          cameras: Annotated[Optional[str], typer.Option(help="comma-separated static cameras (default: all static cameras)")] = None,
          whole_recording: Annotated[bool, typer.Option("--whole-recording", help="a video camera without a plate gets the median of its whole file, not of the take (a performer who stays put through a short take is in the take's median)")] = False,
          drop_shadows: Annotated[bool, typer.Option("--drop-shadows", help="leave the performers' shadows on the set out of the masks: a pixel that is the plate darkened to 45-85 percent of its brightness with its colour kept (a performer in the wall's colour, darker, reads so too)")] = False,
          json_out: JsonOpt = False) -> None:
    """Compute performer masks against background plates into the capture folder's masks folder."""
    from volcap_core.masks import write_plate_masks

    t0 = time.perf_counter()
    progress, update = _progress("masks")
    with progress:
        written = write_plate_masks(capture_dir, plates=plates,
                                    cameras=[c for c in cameras.split(",") if c] if cameras else None,
                                    whole_recording=whole_recording, drop_shadows=drop_shadows,
                                    progress=lambda cam, done, total: update(done, total))
    wall = time.perf_counter() - t0
    _emit({"cameras": written, "wall_s": round(wall, 3)}, json_out,
          f"wrote {sum(written.values())} masks of {len(written)} camera(s) into {capture_dir} in {wall:.1f} s")


@app.command(name="ingest")
def ingest_cmd(capture_dir: Annotated[Path, typer.Argument(help="capture folder holding capture.json")],
               store: StoreOpt = DEFAULT_STORE,
               nan_policy: Annotated[str, typer.Option(help="'error' refuses NaN/Inf pixels, 'repair' replaces them")] = "error",
               json_out: JsonOpt = False) -> None:
    """Check a capture folder and store every frame as scene-linear half EXR plus a Capture record."""
    start_api_early()
    from flows.ingest import ingest_flow

    if nan_policy not in ("error", "repair"):
        raise typer.BadParameter("must be 'error' or 'repair'", param_hint="--nan-policy")
    summary = _run(ingest_flow, store=_store_url(store), capture_dir=str(capture_dir), nan_policy=nan_policy)
    ref = summary.result
    _emit({"capture": ref.model_dump(mode="json"), **summary.counts()}, json_out, f"capture: {ref.digest}")


@app.command()
def demo(store: StoreOpt = DEFAULT_STORE,
         out: Annotated[Path, typer.Option(help="where the demo capture folder is written")] = Path("./demo"),
         frames: Annotated[int, typer.Option(min=2)] = 24,
         enhancer_preset: Annotated[str, typer.Option(help="the close-up's enhancer: demo (the demo preset's smoke run, seconds) or long (the enhancer bench's model and steps, about an hour on 2 cores)")] = "demo",
         json_out: JsonOpt = False) -> None:
    """Make the built-in demo capture and run every stage that exists on it: the reconstruction, then
    a production with an enhanced close-up of one actor."""
    start_api_early()
    from flows.demo import ENHANCER_RUNS, demo_flow

    if enhancer_preset not in ENHANCER_RUNS:
        raise typer.BadParameter(" or ".join(ENHANCER_RUNS), param_hint="--enhancer-preset")

    capture_dir = out / "capture"
    if not (capture_dir / "capture.json").exists():
        with CANCEL.nested():  # its line is not the demo's result: a signal still cancels
            synth(capture_dir, rig="demo_scene", seed=0, frames=frames, depth=True, plates=True, json_out=False)
    summary = _run(demo_flow, store=_store_url(store), capture_dir=str(capture_dir.resolve()),
                   out_dir=str(out.resolve()), enhancer=enhancer_preset)
    refs = summary.result
    lines = [f"  {k}: {v['digest'] if isinstance(v, dict) and 'digest' in v else v}" for k, v in refs.items()
             if k != "closeup"]
    closeup = refs["closeup"]
    face = closeup["face"]
    lines += ["close-up:", *(f"  {k}: {closeup[k]}" for k in ("sheet", "scores", "spec", "face_capture", "resolution")),
              *(f"  {k} frames: {v}" for k, v in closeup["frames"].items()),
              "  face region (PSNR dB / SSIM / detail): " + "; ".join(
                  f"{row} {f['psnr']} / {f['ssim']} / {f['detail']}" for row, f in face.items()),
              f"  {closeup['enhancer_budget']}", f"  {closeup['enhancer_pairs']}"]
    _emit({**refs, **summary.counts()}, json_out,
          f"demo results in store {_store_url(store)} and {out}:\n" + "\n".join(lines))


@app.command()
def reconstruct(capture: Annotated[str, typer.Argument(help="capture ref name (captures/NAME) or digest")],
                frames: Annotated[Optional[str], typer.Option(help="take frames A:B (B exclusive); all when omitted")] = None,
                preset: Annotated[str, typer.Option(help="quality preset (training and segments; the table productions use): test, demo, preview, production")] = "demo",
                degrees: Annotated[str, typer.Option(help="model: poly4dgs, rotor4d, static")] = "poly4dgs",
                segment_frames: Annotated[Optional[int], typer.Option(help="at most this many frames per segment, neighbours sharing the preset's overlap (default: the preset's segments)")] = None,
                steps: Annotated[Optional[int], typer.Option(help="train this many steps instead of the preset's (its schedule stretched to match)")] = None,
                max_gaussians: Annotated[Optional[int], typer.Option(help="Gaussian budget of every segment (MCMC's cap; training starts at 70 % of it); default: the preset's plan, gaussians_per_frame a frame within max_gaussians_per_segment, as a production trains")] = None,
                calibration: Annotated[Optional[str], typer.Option(help="Calibration ref; estimated here (cached) when omitted")] = None,
                points: Annotated[Optional[str], typer.Option(help="PointCloudSequence ref; dense points of the frames when omitted")] = None,
                ground_truth: Annotated[bool, typer.Option("--ground-truth", help="use a synthetic capture's true cameras and depth points instead of estimating them")] = False,
                held_out: Annotated[Optional[str], typer.Option(help="comma-separated cameras never trained on")] = None,
                allow_unregistered: Annotated[bool, typer.Option("--allow-unregistered", help="the calibration run here (no --calibration) leaves out (and lists) a static or tracking camera the adjustment cannot support instead of failing, as volcap calibrate --allow-unregistered; training leaves it out")] = False,
                known_distance: Annotated[Optional[str], typer.Option(help="CAM_A,CAM_B,METRES for the calibration run here (no --calibration), as volcap calibrate --known-distance")] = None,
                known_points: Annotated[Optional[Path], typer.Option(help="JSON of named scene points and their measured distance for the calibration run here (no --calibration), as volcap calibrate --known-points")] = None,
                min_pair_inliers: Annotated[Optional[int], typer.Option(min=8, help="for the calibration run here (no --calibration), as volcap calibrate --min-pair-inliers")] = None,
                seed: Annotated[int, typer.Option()] = 0,
                mask_alpha: Annotated[Optional[str], typer.Option(help="WEIGHT[:EVERY]: train the performers' alpha toward the capture's own masks (imported or from volcap masks) with this L1 weight, on every EVERY-th step (default 1); the preset's mask_alpha_weight / mask_alpha_every replaced. A capture without masks trains as without it")] = None,
                set_frozen_from: Annotated[Optional[float], typer.Option(min=0.0, max=0.99, help="from this fraction of the steps on, the set (the static Gaussians) stops training and the performers train alone over its render (docs/poly4dgs.md, 'The set frozen'); 0: the set trains to the end; default: the preset's (none sets it)")] = None,
                out: Annotated[Path, typer.Option(help="folder for each segment's contact sheet PNG")] = Path("reconstruct"),
                store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Train the Poly4DGS segments of an ingested capture; reports held-out PSNR/SSIM (per-camera gain/offset
    fitted on other frames), raw and on the performers, beside the empty- and untrained-model floors, and
    writes a contact sheet (footage | render | error) per segment."""
    start_api_early()
    from flows.reconstruct import reconstruct_flow

    span = _frame_span(frames)
    held = [c for c in held_out.split(",") if c] if held_out is not None else None
    alpha = _mask_alpha(mask_alpha) if mask_alpha is not None else None
    distance, marks = _scale_options(known_distance, known_points)
    given = [o for o, v in (("--allow-unregistered", allow_unregistered), ("--known-distance", distance),
                            ("--known-points", marks), ("--min-pair-inliers", min_pair_inliers)) if v]
    if given and (calibration or ground_truth):
        raise typer.BadParameter(f"{', '.join(given)} set the calibration reconstruct runs itself; with "
                                 f"{'--calibration' if calibration else '--ground-truth'} it runs none "
                                 "(pass them to volcap calibrate instead)", param_hint=given[0])
    extra = {k: v for k, v in (("allow_unregistered", allow_unregistered), ("known_distance", distance),
                               ("known_points", marks), ("min_pair_inliers", min_pair_inliers)) if v}
    summary = _run(reconstruct_flow, store=_store_url(store), capture=capture, frames=span, preset=preset,
                   degrees=degrees, segment_frames=segment_frames, calibration=calibration, points=points,
                   held_out=held, seed=seed, ground_truth=ground_truth, steps=steps, max_gaussians=max_gaussians,
                   mask_alpha=alpha, set_frozen_from=set_frozen_from, **extra)
    result = summary.result
    st = _open(_store_url(store))
    lines = []
    for seg in result["segments"]:
        a, b = seg["frames"]
        if seg["contact_sheet"]:
            path = out / f"contact_sheet_{a:06d}_{b:06d}.png"
            st.get_file(seg["contact_sheet"]["digest"], path)
            seg["contact_sheet_png"] = str(path)
        lines.append(f"  segment {a}:{b}: {seg['model']['digest']}  {seg['gaussians']} Gaussians, "
                     f"{seg['train_wall_s']:.1f} s training\n"
                     f"    held-out PSNR {_fmt(seg['held_out_psnr'])} dB, SSIM {_fmt(seg['held_out_ssim'], 3)} "
                     f"(raw {_fmt(seg['held_out_psnr_raw'])} dB; performers {_fmt(seg['held_out_psnr_performers'])} dB)\n"
                     f"    floors on the same views: empty model {_fmt(seg['floor_empty_psnr'])} dB, untrained "
                     f"{_fmt(seg['floor_initial_psnr'])} dB; training views {_fmt(seg['training_psnr'])} dB\n"
                     + _alpha_line(seg["scores"].get("alpha", {})) +
                     f"    contact sheet: {seg.get('contact_sheet_png', 'none')}")
    _emit({**result, **summary.counts()}, json_out, "\n".join(lines))


def _alpha_line(alpha: dict) -> str:
    """The performers' alpha on the held-out views, per camera role, beside its floors (``scores.alpha``;
    empty without performer masks)."""
    if not alpha:
        return ""
    roles = "; ".join(f"{role} " + ", ".join(f"{m} {a[m]['error']:.3f} / {a[m]['on']:.3f} / {a[m]['spill']:.3f}"
                                            for m in ("trained", "initial", "empty")) for role, a in alpha.items())
    return f"    performers' alpha on the held-out views (|A - M| / on the performers / spill): {roles}\n"


def _read_json(path: Path) -> Any:
    """A JSON file given on the command line; a :class:`CommandError` naming it when it cannot be
    read or parsed."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CommandError(f"{path}: not a readable JSON file: {exc}") from None


def _scale_options(known_distance: str | None, known_points: Path | None
                   ) -> tuple[tuple[str, str, float] | None, dict | None]:
    """``--known-distance CAM_A,CAM_B,METRES`` -> (a, b, metres); ``--known-points FILE`` -> its
    JSON, checked (:class:`~volcap_core.calibration.scale.KnownPoints`); not both."""
    if known_distance is not None and known_points is not None:
        raise typer.BadParameter("give either --known-distance (between two cameras) or --known-points, not both",
                                 param_hint="--known-points")
    distance = None
    if known_distance is not None:
        parts = known_distance.split(",")
        try:
            distance = (parts[0].strip(), parts[1].strip(), float(parts[2]))
            if len(parts) != 3 or not distance[2] > 0:
                raise ValueError
        except (ValueError, IndexError):
            raise typer.BadParameter("expected CAM_A,CAM_B,METRES with a positive distance, e.g. S000,S004,8.41",
                                     param_hint="--known-distance") from None
    marks = None
    if known_points is not None:
        from volcap_core.calibration.errors import KnownPointsError
        from volcap_core.calibration.scale import KnownPoints

        marks = _read_json(known_points)
        try:
            KnownPoints.parse(marks, str(known_points))
        except KnownPointsError as exc:
            raise CommandError(str(exc)) from None
    return distance, marks


def _frame_span(frames: str | None) -> tuple[int, int] | None:
    """``--frames A:B`` (B exclusive) -> (A, B); None when omitted."""
    if not frames:
        return None
    try:
        a, b = (int(x) for x in frames.split(":"))
    except ValueError:
        raise typer.BadParameter("expected A:B, e.g. 0:24", param_hint="--frames") from None
    return a, b


def _mask_alpha(value: str) -> tuple[float, int]:
    """``--mask-alpha WEIGHT[:EVERY]`` -> (weight, every); every defaults to 1."""
    weight, _, every = value.partition(":")
    try:
        w, n = float(weight), int(every) if every else 1
    except ValueError:
        raise typer.BadParameter(f"expected WEIGHT[:EVERY], e.g. 1 or 1:4, not {value!r}", param_hint="--mask-alpha") from None
    if w < 0 or n < 1:
        raise typer.BadParameter(f"WEIGHT must be >= 0 and EVERY >= 1, not {value!r}", param_hint="--mask-alpha")
    return w, n


# ---------------------------------------------------------------------------------------------
# calibrate / export-colmap
# ---------------------------------------------------------------------------------------------


@app.command()
def calibrate(capture: Annotated[str, typer.Argument(help="capture ref name (captures/NAME) or digest")],
              frames: Annotated[Optional[str], typer.Option(help="dense points for take frames A:B (B exclusive); all when omitted")] = None,
              allow_unregistered: Annotated[bool, typer.Option("--allow-unregistered", help="leave out (and list) a static or tracking camera the adjustment cannot support instead of failing; training leaves it out")] = False,
              colour_charts: Annotated[Optional[Path], typer.Option(help="also calibrate colour between the rigs: the JSON file of volcap calibrate-colour (Face Rig onto Scene Rig)")] = None,
              instants: Annotated[int, typer.Option(min=1, help="take instants pooled into the static cameras' SfM, spread over the take (a sparse or dark background); 1: the middle frame alone")] = 1,
              known_distance: Annotated[Optional[str], typer.Option(help="CAM_A,CAM_B,METRES: measured distance between two static cameras' optical centres, the scale of a capture without a lidar scan (default: the rig's mounts)")] = None,
              known_points: Annotated[Optional[Path], typer.Option(help="JSON file: named scene points (marks on the floor, a scale bar's ends) by their pixels in two or more static cameras and the measured distance between them, the scale of a capture without a lidar scan (docs/calibration.md)")] = None,
              min_pair_inliers: Annotated[Optional[int], typer.Option(min=8, help="verified matches a pair of static cameras needs in the static SfM (default 36, for close neighbours; a sparse rig of wide baselines needs ~20, docs/calibration.md)")] = None,
              no_points: Annotated[bool, typer.Option("--no-points", help="the calibration alone, without the dense points (volcap reconstruct computes them)")] = False,
              against: Annotated[Optional[str], typer.Option("--against", help="a Calibration ref the studio trusts (imported-calibrations/NAME): print each static camera's rotation, centre and focal against it beside its stated sigma")] = None,
              store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Calibrate every camera of an ingested capture and compute per-frame dense points.

    Prints the Calibration and point-cloud refs (also named calibrations/NAME and points/NAME) and,
    for a capture with ground truth (synthetic), the error table; with --against, each static
    camera against a trusted calibration; --json adds it all as JSON.
    """
    start_api_early()
    from flows.calibrate import calibrate_flow

    charts = None
    if colour_charts is not None:
        charts = _read_json(colour_charts)
    distance, marks = _scale_options(known_distance, known_points)
    summary = _run(calibrate_flow, store=_store_url(store), capture=capture, frames=_frame_span(frames),
                   allow_unregistered=allow_unregistered, colour_charts=charts, instants=instants,
                   known_distance=distance, known_points=marks, points=not no_points, against=against,
                   **({"min_pair_inliers": min_pair_inliers} if min_pair_inliers is not None else {}),
                   colour_base_dir=str(colour_charts.resolve().parent) if colour_charts is not None else None)
    out = summary.result
    lines = [f"calibration: {out['calibration']['digest']}",
             f"points: {out['points']['digest']}" if out["points"] else "points: not computed (--no-points)"]
    lines += [f"left out (unregistered): {cam}: {why}" for cam, why in out["unregistered"].items()]
    lines += [f"warning: {line}" for line in out.get("warnings", [])]
    sf = out.get("stage_frame") or {}
    if "mount_residual_rms_m" in sf:
        from flows.calibrate import scale_source_text

        lines.append(f"no lidar scan: stage frame and scale from the {scale_source_text(sf)}; camera centres "
                     f"{100 * sf['mount_residual_rms_m']:.1f} cm rms (max {100 * sf['mount_residual_max_m']:.1f} cm) "
                     f"from their mounts")
    if "known_points_distance_m" in sf:
        from flows.calibrate import known_points_text

        lines.append("known points: " + known_points_text(sf, "mount_residual_rms_m" not in sf))
    if out["errors"] is not None:
        lines += _error_lines(out["errors"])
    if out.get("against"):
        lines.append(f"against {against}:")
        lines += [f"  {cam}: rotation {e['rotation_deg']:.3f}° (stated σ {_fmt(e['rotation_sigma_deg'], 3)}°), "
                  f"centre {100 * e['centre_m']:.1f} cm (σ {_fmt(100 * e['centre_sigma_m'] if e['centre_sigma_m'] is not None else None, 1)} cm), "
                  f"focal {e['focal_pct']:+.2f} % (σ {_fmt(e.get('focal_sigma_pct'))} %), principal point {e['principal_px']:.1f} px"
                  for cam, e in out["against"].items()]
    if out.get("colour"):
        lines += _colour_lines(out["colour"])
    _emit({**out, **summary.counts()}, json_out, "\n".join(lines))


@app.command(name="calibrate-colour")
def calibrate_colour_cmd(charts: Annotated[Path, typer.Argument(help="JSON file: {\"face\": VIEW, \"scene\": VIEW}, each VIEW a chart seen by that rig (docs/calibration.md)")],
                         onto: Annotated[str, typer.Option(help="the rig the other one is mapped onto: scene or face")] = "scene",
                         name: Annotated[Optional[str], typer.Option(help="store the record as colour/NAME (default colour/SOURCE-to-REFERENCE)")] = None,
                         store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Colour matrix between the Face Rig and the Scene Rig from a colour chart seen by each.

    Prints the record's ref, the 3x3 matrix and offset, and the chart's colour error (ΔE2000)
    before and after; --json adds it all as JSON.
    """
    spec = _read_json(charts)
    start_api_early()
    from flows.calibrate import calibrate_colour_flow

    summary = _run(calibrate_colour_flow, store=_store_url(store), charts=spec, onto=onto, name=name,
                   base_dir=str(charts.resolve().parent))
    out = summary.result
    _emit({**out, **summary.counts()}, json_out, "\n".join(_colour_lines(out)))


def _colour_lines(c: dict) -> list[str]:
    b, a = c["before"], c["after"]
    return [f"colour {c['source_rig']} -> {c['reference_rig']}: {c['colour']['digest']}",
            "  matrix " + "; ".join(" ".join(f"{v:.4f}" for v in row) for row in c["matrix"])
            + "  offset " + " ".join(f"{v:.4f}" for v in c["offset"]),
            f"  chart ({c['patches']} patches): ΔE2000 mean {a['delta_e2000_mean']:.2f}, max {a['delta_e2000_max']:.2f} "
            f"(before: mean {b['delta_e2000_mean']:.2f}, max {b['delta_e2000_max']:.2f})"]


def _error_lines(t: dict) -> list[str]:
    """The calibration error table (volcap_core.calibration.metrics) as a few human lines."""
    lines = []
    s = t.get("static") or {}
    if s:
        lines.append(f"static cameras ({s['cameras']}): rotation mean {_fmt(s['rotation_deg_mean'], 3)}° max "
                     f"{_fmt(s['rotation_deg_max'], 3)}°; centre max {_fmt(_pct(s['centre_frac_max']))}% of stage; "
                     f"|focal| max {_fmt(s['focal_pct_max_abs'])}%; projection mean {_fmt(s['projection_px_mean'])} px")
    for variant, v in (t.get("tracking") or {}).items():
        lines.append(f"tracking cameras [{variant}]: |focal| mean {_fmt(v['focal_pct_mean_abs'])}% max "
                     f"{_fmt(v['focal_pct_max_abs'])}%; rotation mean {_fmt(v['rotation_deg_mean'], 3)}°; pose jitter "
                     f"mean {_fmt(v['pose_jitter_px_mean'])} px; focal jitter mean {_fmt(v['focal_jitter_px_mean'])} px")
    p = t.get("points") or {}
    if p.get("per_frame"):
        med = p.get("median_distance_m")
        lines.append(f"dense points: {p['points_mean']:.0f} per frame over {len(p['per_frame'])} frame(s), median "
                     f"distance to the true surface {_fmt(None if med is None else 1000 * med, 1)} mm")
    if t.get("targets"):
        lines.append("targets: " + ", ".join(f"{k} {'met' if v else 'not met'}" for k, v in t["targets"].items()))
    return lines


def _pct(x: float | None) -> float | None:
    return None if x is None else 100 * x


@app.command(name="export-colmap")
def export_colmap_cmd(calibration: Annotated[str, typer.Argument(help="Calibration ref (digest or calibrations/NAME)")],
                      frame: Annotated[int, typer.Option("--frame", help="take index")],
                      out: Annotated[Path, typer.Option("--out", help="output folder (a COLMAP model)")],
                      points: Annotated[Optional[str], typer.Option(help="PointCloudSequence ref whose points of that frame go in points3D")] = None,
                      binary: Annotated[bool, typer.Option("--binary", help="write .bin files instead of .txt")] = False,
                      store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Write one frame's cameras (and dense points) as a COLMAP model that gsplat, nerfstudio and
    COLMAP's GUI open."""
    from volcap_core.calibration.colmap_export import cameras_at, export_colmap
    from volcap_core.segment import tracking_frames
    from volcap_core.calibration.record import Calibration
    from volcap_core.pointcloud import PointCloudSequence, decode_points

    s = _open(store)
    calib_ref = s.resolve(calibration)
    calib = s.get_record(calib_ref, Calibration)
    if not 0 <= frame < calib.frame_count:
        raise CommandError(f"frame {frame} outside [0, {calib.frame_count}) of the calibration of {calib.capture}")
    cams = cameras_at(calib, frame, tracking_frames(s.get_bytes, calib))
    xyz = rgb = None
    if points:
        seq = s.get_record(s.resolve(points), PointCloudSequence)
        if seq.calibration.digest != calib_ref.digest:
            raise CommandError(f"points {points} were made with calibration {seq.calibration.digest}, "
                               f"not {calib_ref.digest}")
        try:
            pf = seq.at(frame)
        except KeyError:
            raise CommandError(f"points {points} have no frame {frame} (frames "
                               f"{', '.join(str(f.frame) for f in seq.frames) or 'none'})") from None
        xyz, rgb = decode_points(s.get_bytes(pf.points))
    _replace_dir_atomic(out, lambda tmp: export_colmap(tmp, cams, xyz, rgb, binary=binary))
    _emit({"out": str(out), "frame": frame, "cameras": len(cams), "points": 0 if xyz is None else len(xyz),
           "binary": binary}, json_out, f"{out}: {len(cams)} cameras, {0 if xyz is None else len(xyz)} points "
                                        f"({'binary' if binary else 'text'})")


COLMAP_MODEL_FILES = {f"{n}.{e}" for n in ("cameras", "images", "points3D", "rigs", "frames") for e in ("txt", "bin")}


def _replace_dir_atomic(path: Path, write) -> None:
    """``write(tmp_dir)`` into a temporary folder beside ``path``, then rename it to ``path``. An
    existing COLMAP model there is replaced; any other existing content is refused."""
    import os
    import shutil
    import tempfile

    if path.exists():
        if not path.is_dir() or not {p.name for p in path.iterdir()} <= COLMAP_MODEL_FILES:
            raise CommandError(f"{path} exists and is not a COLMAP model folder: choose another --out")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part"))
    old = None
    try:
        write(tmp)
        if path.exists():
            old = path.with_name(f".{path.name}.{os.getpid()}.old")
            os.replace(path, old)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not path.exists():
            os.replace(old, path)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@app.command(name="import-calibration")
def import_calibration_cmd(source: Annotated[str, typer.Argument(help="Qualisys .qca.txt, OpenCV YAML/JSON file, COLMAP model folder, or (--format record) a stored Calibration's ref")],
                           fmt: Annotated[str, typer.Option("--format", help="qualisys, colmap, opencv, or record (a calibration in the store, solved or imported, applied to this capture's frames)")],
                           capture: Annotated[str, typer.Option("--capture", help="the capture it calibrates; a stored captures/NAME gives frames, fps and frame sizes")],
                           frames: Annotated[Optional[int], typer.Option("--frames", min=1, help="frame count (default: the stored capture's)")] = None,
                           fps: Annotated[Optional[float], typer.Option("--fps", min=0.001, help="frame rate (default: the stored capture's)")] = None,
                           metres_per_unit: Annotated[float, typer.Option("--metres-per-unit", help="COLMAP/OpenCV translations' unit in metres (0.001 for mm); Qualisys is mm by definition")] = 1.0,
                           refine: Annotated[bool, typer.Option("--refine", help="refine the poses against the stored capture's footage (bundle adjustment; the file's world frame and lenses kept)")] = False,
                           refine_intrinsics: Annotated[bool, typer.Option("--refine-intrinsics", help="with --refine: focal lengths and principal points too, around the file's")] = False,
                           refine_instants: Annotated[int, typer.Option("--refine-instants", min=1, help="with --refine: instants of the take pooled (the middle frame first)")] = 1,
                           frame_size: Annotated[Optional[list[str]], typer.Option("--frame-size", metavar="ID=WxH", help="a camera's frame size when no stored capture gives it (its videos re-encoded or resampled since the calibration); repeat per camera")] = None,
                           write_rig: Annotated[Optional[Path], typer.Option("--write-rig", help="also write a rig JSON for the capture folder: each camera's lens calibration as its measured intrinsics, its pose as its mount, at its frames' size")] = None,
                           store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Store a studio's calibration as a Calibration record, named imported-calibrations/NAME, and
    print its ref (a Calibration ref, as `export-colmap` takes). A camera of a stored capture
    whose frames were resampled since (another size) gets the intrinsics of its frames: resized, or
    scaled uniformly and centred (docs/calibration.md, "Importing a studio's calibration").
    `--format record`: SOURCE is a Calibration already in the store (a solved one of the full-size
    footage), applied to the capture's frames the same way. `--refine`: the poses (and with
    `--refine-intrinsics` the focal lengths and principal points) refined against the capture's
    frames; each camera's move and σ printed, a camera that shares nothing with the others kept
    as imported (docs/calibration.md, "Refining an imported calibration"). `--write-rig PATH`: a rig
    for the capture folder written from the (refined) calibration, so a studio that trusts its
    calibration ingests without typing one (docs/calibration.md, "A rig from an imported calibration")."""
    from volcap_core.calibration import importers
    from volcap_core.calibration.record import Calibration
    from volcap_core.capture import Capture
    from volcap_core.store import MissingRefError

    if fmt not in ("qualisys", "colmap", "opencv", "record"):
        raise CommandError(f"--format {fmt!r}: one of qualisys, colmap, opencv, record")
    if fmt in ("qualisys", "record") and metres_per_unit != 1.0:
        raise CommandError(f"--metres-per-unit: a {'Qualisys calibration is in mm by definition' if fmt == 'qualisys' else 'stored calibration is in metres'}")
    s = _open(store)
    if fmt != "record":
        source = Path(source)
        if not source.exists():
            raise CommandError(f"{source}: no such file or folder")
        if (fmt == "colmap") != source.is_dir():
            raise CommandError(f"{source}: --format {fmt} reads {'a folder' if fmt == 'colmap' else 'a file'}")
    try:
        cap = s.get_record(s.get_ref(f"captures/{capture}"), Capture)
    except MissingRefError:
        cap = None
    frames = frames if frames is not None else (cap.frame_count if cap else None)
    fps = fps if fps is not None else (cap.fps if cap else None)
    if frames is None or fps is None:
        raise CommandError(f"no capture captures/{capture} in the store: give --frames and --fps")
    sizes = {c.id: (c.width, c.height) for c in cap.cameras} if cap else {}   # the ingested frames'
    for item in frame_size or ():
        cid, _, wh = item.partition("=")
        w, _, h = wh.lower().partition("x")
        if not cid or not w.isdigit() or not h.isdigit() or int(w) < 1 or int(h) < 1:
            raise CommandError(f"--frame-size {item!r}: expected ID=WxH, e.g. cam01=1080x1920")
        if cid in sizes and sizes[cid] != (int(w), int(h)):
            raise CommandError(f"--frame-size {item}: stored capture {capture}'s camera {cid} has "
                               f"{sizes[cid][0]}x{sizes[cid][1]} frames")
        sizes[cid] = (int(w), int(h))
    kw = dict(capture=capture, frame_count=frames, fps=fps)
    if fmt == "colmap":
        read = lambda fs: importers.calibration_from_colmap(source, metres_per_unit=metres_per_unit, frame_sizes=fs, **kw)  # noqa: E731
    elif fmt == "opencv":
        read = lambda fs: importers.calibration_from_opencv(source.read_bytes(), source=str(source), metres_per_unit=metres_per_unit, frame_sizes=fs, **kw)  # noqa: E731
    elif fmt == "qualisys":
        read = lambda fs: importers.calibration_from_qualisys(source.read_bytes(), source=str(source), frame_sizes=fs, **kw)  # noqa: E731
    else:
        try:
            stored = s.get_record(s.resolve(source), Calibration)
        except MissingRefError:
            raise CommandError(f"{source}: no such calibration in the store (a digest or a name such as "
                               f"calibrations/NAME)") from None
        except (ValueError, TypeError) as exc:
            raise CommandError(f"{source}: not a Calibration record: {exc}") from None
        read = lambda fs: importers.fit_calibration(stored, fs, source=source, **kw)  # noqa: E731
    if (refine_intrinsics or refine_instants != 1) and not refine:
        raise CommandError("--refine-intrinsics and --refine-instants go with --refine")
    if refine and cap is None:
        raise CommandError(f"--refine: no capture captures/{capture} in the store to refine against (ingest it first)")
    ids = {c.id for c in read(None).cameras}
    unknown = sorted(c for c in (item.partition("=")[0] for item in frame_size or ()) if c not in ids)
    if unknown:
        raise CommandError(f"--frame-size: {', '.join(unknown)} not in the calibration {source} "
                           f"(its cameras: {', '.join(sorted(ids))})")
    record = read({c: wh for c, wh in sizes.items() if c in ids})
    refined = None
    if refine:
        from volcap_core.calibration.inputs import frame_loader
        from volcap_core.calibration.refine_import import RefineOptions, refine_imported
        from volcap_core.calibration.static import StaticCalibrationOptions, instant_frames

        load = frame_loader(s.get_bytes, cap)
        shared = [c for c in sorted(ids) if c in sizes]
        instants = instant_frames(cap.frame_count, cap.frame_count // 2, StaticCalibrationOptions(instants=refine_instants))
        record, refined = refine_imported(record, [{c: load(c, k) for c in shared} for k in instants],
                                          RefineOptions(intrinsics=refine_intrinsics))
    rig_doc = None
    if write_rig is not None:
        from volcap_core.calibration.rig_from_calibration import rig_from_calibration

        try:
            rig_doc = rig_from_calibration(record).model_dump(mode="json")
        except ValueError as exc:
            raise CommandError(f"--write-rig {write_rig}: {str(exc).splitlines()[0]}") from None
    ref = s.put_record(record)
    s.set_ref(f"imported-calibrations/{capture}", ref)
    if rig_doc is not None:
        _write_atomic(write_rig, (json.dumps(rig_doc, indent=2) + "\n").encode())
    lines = [f"calibration imported-calibrations/{capture}: {ref.digest}"]
    if rig_doc is not None:
        lines.append(f"rig {write_rig}: {len(rig_doc['cameras'])} static cameras, lens calibrations as measured "
                     f"intrinsics, poses as mounts")
    for c in record.cameras:
        if c.intrinsics is None:
            lines.append(f"  {c.id}: {c.width}x{c.height}, tracking camera (intrinsics per frame)")
            continue
        fx, fy, cx, cy = c.intrinsics
        note = ""
        if "resample_scale" in c.quality:
            sx, sy = c.quality["resample_scale"], c.quality.get("resample_scale_y", c.quality["resample_scale"])
            note = f", frames {c.width}x{c.height} scaled by {sx:.5f}" + (f" x {sy:.5f}" if sy != sx else "")
        lines.append(f"  {c.id}: {c.width}x{c.height}, fx {fx:.1f} fy {fy:.1f} cx {cx:.1f} cy {cy:.1f}, "
                     f"{len(c.distortion)} distortion coefficients{note}")
        if refined is not None and c.id in refined.cameras:
            r = refined.cameras[c.id]
            lines.append(f"    refined: moved {r['rotation_moved_deg']:.3f}° and {100 * r['centre_moved_m']:.1f} cm "
                         f"(σ {_fmt(r.get('rotation_sigma_deg'), 3)}° and {_fmt(100 * r['centre_sigma_m'] if 'centre_sigma_m' in r else None, 1)} cm), "
                         f"{r['observations']:.0f} observations at {r['reprojection_px']:.2f} px median"
                         + (f", focal {100 * r['focal_moved_rel']:+.2f} %" if "focal_moved_rel" in r else ""))
        elif refined is not None and c.id in refined.kept:
            lines.append(f"    kept as imported: {refined.kept[c.id]}")
    if record.unregistered:
        lines.append("  left out: " + "; ".join(f"{k}: {v}" for k, v in sorted(record.unregistered.items())))
    missing = sorted(set(sizes) - ids)
    if missing:
        lines.append(f"  capture cameras without a calibration: {', '.join(missing)}")
    _emit({"calibration": ref.model_dump(mode="json"), "name": f"imported-calibrations/{capture}",
           "cameras": sorted(ids), "unregistered": record.unregistered, "capture_cameras_missing": missing,
           **({"refined": refined.cameras, "kept_imported": refined.kept} if refined is not None else {}),
           **({"rig": str(write_rig)} if rig_doc is not None else {})},
          json_out, "\n".join(lines))


def _fmt(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _camera_args(s, seg, camera: str | None, camera_json: Path | None, time_s: float):
    """(K, world_to_camera, width, height) from a calibrated camera id or a camera JSON file."""
    import numpy as np

    if camera_json is not None:
        doc = _read_json(camera_json)
        try:
            return np.asarray(doc["K"], float), np.asarray(doc["world_to_camera"], float), int(doc["width"]), int(doc["height"])
        except KeyError as exc:
            raise CommandError(f"{camera_json}: camera JSON needs K, world_to_camera, width, height (missing {exc})") from None
    if camera is None:
        raise CommandError("give --camera ID (a calibrated camera of the capture) or --camera-json FILE")
    from volcap_core.calibration.record import Calibration, camera_at
    from volcap_core.segment import tracking_frames

    calib = s.get_record(seg.calibration, Calibration)
    frame = min(max(int(round(time_s * seg.fps)), 0), calib.frame_count - 1)
    try:
        return camera_at(calib, camera, frame, tracking_frames(s.get_bytes, calib))
    except KeyError:
        raise CommandError(f"camera {camera!r} is not in the calibration "
                           f"({', '.join(c.id for c in calib.cameras)})") from None


@app.command()
def render(model: Annotated[str, typer.Argument(help="segment model ref (digest or ref name)")],
           time_s: Annotated[float, typer.Option("--time", help="seconds on the take's clock")],
           out: Annotated[Path, typer.Option("--out", help="output .exr (linear RGBA, half float)")],
           camera: Annotated[Optional[str], typer.Option(help="a calibrated camera id of the capture")] = None,
           camera_json: Annotated[Optional[Path], typer.Option(help="JSON with K, world_to_camera (OpenCV), width, height")] = None,
           grids: Annotated[bool, typer.Option(help="apply that camera's fitted exposure/black-level grids")] = False,
           store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Render a segment model from a capture camera or any camera at time T to an EXR."""
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.segment import render_segment_exr

    s = _open(store)
    seg = s.get_record(s.resolve(model), SegmentModel)
    K, w2c, w, h = _camera_args(s, seg, camera, camera_json, time_s)
    data = render_segment_exr(s.get_bytes, seg, K, w2c, w, h, time_s, camera if grids else None)
    _write_atomic(out, data)
    _emit({"out": str(out), "width": w, "height": h, "time_s": time_s}, json_out, str(out))


@app.command(name="export-ply")
def export_ply_cmd(model: Annotated[str, typer.Argument(help="segment model ref (digest or ref name)")],
                   time_s: Annotated[float, typer.Option("--time", help="seconds on the take's clock")],
                   out: Annotated[Path, typer.Option("--out", help="output .ply (standard 3DGS layout)")],
                   store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Export the Gaussians of a segment at time T as a 3DGS PLY that splat viewers open."""
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.splat import export_ply, load_model

    s = _open(store)
    seg = s.get_record(s.resolve(model), SegmentModel)
    data = export_ply(load_model(s.get_bytes(seg.model)), time_s)
    _write_atomic(out, data)
    _emit({"out": str(out), "bytes": len(data)}, json_out, str(out))


def _write_atomic(path: Path, data: bytes) -> None:
    """An output file the user named: its folder is made if missing (``--out renders/a.exr``
    in a fresh checkout), then the file is replaced atomically."""
    from volcap_core.files import write_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, data)


# ---------------------------------------------------------------------------------------------
# store
# ---------------------------------------------------------------------------------------------


def _open(url: str):
    from volcap_core.store import ArtifactStore
    return ArtifactStore(url)


@store_app.command("ls")
def store_ls(prefix: Annotated[str, typer.Argument(help="only refs starting with this")] = "",
             store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """List named refs (roots)."""
    refs = _open(store).list_refs(prefix)
    for name, ref in refs.items():
        typer.echo(f"{name}\t{ref.digest}\t{ref.size}\t{ref.media_type}")
    if json_out:
        typer.echo(json.dumps({n: r.model_dump(mode="json") for n, r in refs.items()}, sort_keys=True))


@store_app.command("put")
def store_put(path: Annotated[Path, typer.Argument(exists=True, help="file or folder to store")],
              name: Annotated[Optional[str], typer.Option("--name", help="also set this ref")] = None,
              media_type: Annotated[str, typer.Option(help="media type for a file")] = "application/octet-stream",
              store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Store a file (a blob) or a folder (its files and a tree)."""
    s = _open(store)
    if path.is_dir():
        progress, update = _progress(f"storing {path}")
        with progress:
            ref = s.put_directory(path, progress=update)
    else:
        ref = s.put_file(path, media_type)
    if name:
        s.set_ref(name, ref)
    _emit({"ref": ref.model_dump(mode="json"), "name": name}, json_out, ref.digest)


@store_app.command("get")
def store_get(ref: Annotated[str, typer.Argument(help="digest (blake3:...) or ref name")],
              out: Annotated[Optional[Path], typer.Option("--out", "-o", help="file or folder to write; stdout if omitted")] = None,
              store: StoreOpt = DEFAULT_STORE) -> None:
    """Copy an object out (verified). Trees are written as folders."""
    from volcap_core.records import MEDIA_TREE

    s = _open(store)
    r = s.resolve(ref)
    is_tree = r.media_type == MEDIA_TREE
    if not is_tree and out is None:
        sys.stdout.buffer.write(s.get_bytes(r))
        return
    if out is None:
        raise CommandError(f"{ref} is a tree: give --out FOLDER")
    if is_tree:
        s.get_directory(r, out)
    else:
        s.get_file(r, out)
    typer.echo(str(out))


@store_app.command("verify")
def store_verify(store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Re-hash every object and check every ref's closure is present (exit 1 if not)."""
    progress, update = _progress("verifying")
    with progress:
        report = _open(store).verify(progress=update)
    for d in report.corrupt:
        typer.echo(f"corrupt: {d}", err=True)
    for d in report.dangling:
        typer.echo(f"missing: {d}", err=True)
    _emit({"checked": report.checked, "bytes": report.bytes, "corrupt": report.corrupt,
           "dangling": report.dangling}, json_out,
          f"{report.checked} objects, {report.bytes} bytes checked: "
          f"{len(report.corrupt)} corrupt, {len(report.dangling)} missing")
    if not report.ok:
        raise CommandError(f"store {store} failed verification: {len(report.corrupt)} corrupt, "
                           f"{len(report.dangling)} missing objects")


@store_app.command("gc")
def store_gc(store: StoreOpt = DEFAULT_STORE,
             grace: Annotated[float, typer.Option(help="keep unreachable objects younger than this (seconds)")] = 3600.0,
             dry_run: Annotated[bool, typer.Option("--dry-run", help="report only")] = False,
             json_out: JsonOpt = False) -> None:
    """Delete objects no ref reaches (older than the grace period)."""
    r = _open(store).gc(grace_s=grace, dry_run=dry_run)
    _emit({"deleted": r.deleted, "deleted_bytes": r.deleted_bytes, "kept": r.kept,
           "young_unreachable": r.young_unreachable, "tmp_deleted": r.tmp_deleted, "dry_run": dry_run}, json_out,
          f"{'would delete' if dry_run else 'deleted'} {r.deleted} objects ({r.deleted_bytes} bytes), kept {r.kept} "
          f"({r.young_unreachable} unreachable but younger than {grace:g} s), {r.tmp_deleted} stale temporary files")


@store_app.command("du")
def store_du(store: StoreOpt = DEFAULT_STORE, json_out: JsonOpt = False) -> None:
    """Objects and bytes in the store, and what each ref keeps alive."""
    d = _open(store).du()
    typer.echo(f"{d['objects']} objects, {d['bytes']} bytes")
    for name, v in d["refs"].items():
        typer.echo(f"  {name}: {v['objects']} objects, {v['bytes']} bytes")
    if json_out:
        typer.echo(json.dumps(d, sort_keys=True))


# ---------------------------------------------------------------------------------------------
# production: plan / run / worker
# ---------------------------------------------------------------------------------------------

SpecArg = Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="production spec (YAML)")]
ShotsOpt = Annotated[Optional[list[str]], typer.Option("--shot", help="deliver only this shot (repeatable)")]
SpecStoreOpt = Annotated[Optional[str], typer.Option(
    "--store", help="store URL; default: the spec's store:, else $VOLCAP_STORE")]


@app.command()
def plan(spec: SpecArg, store: SpecStoreOpt = None, shots: ShotsOpt = None, json_out: JsonOpt = False) -> None:
    """Print the steps a production spec needs, each cached or to run (and why); runs nothing."""
    from flows.production import open_production, plan_production

    prod = open_production(spec, _store_url(store) if store else None, shots)
    planned = plan_production(prod)
    todo = [p for p in planned if p.status == "to-run"]
    lines = [f"production {prod.spec.name} (store {prod.store}): {len(planned)} steps, "
             f"{len(planned) - len(todo)} cached, {len(todo)} to run"]
    for p in planned:
        lines.append(f"  {p.status:7s} {p.step.id}" + (f"  ({p.reason})" if p.reason else ""))
    _emit({"production": prod.spec.name, "store": prod.store, "steps": [p.as_json() for p in planned]},
          json_out, "\n".join(lines))


@app.command(name="run")
def run_cmd(spec: SpecArg, store: SpecStoreOpt = None, shots: ShotsOpt = None,
            segment_runs: Annotated[str, typer.Option(
                help="auto: runs of the train-segment deployment when the Prefect server has it, else "
                     "in this process; local; deployment")] = "auto",
            max_attempts: Annotated[int, typer.Option(help="runs of a segment before giving up (crashes)")] = 3,
            json_out: JsonOpt = False) -> None:
    """Build everything a production spec needs (only what is not cached)."""
    start_api_early()
    from flows.production import production_flow

    if segment_runs not in ("auto", "local", "deployment"):
        raise typer.BadParameter("auto, local or deployment", param_hint="--segment-runs")
    summary = _run(production_flow, spec=str(spec.resolve()), store=_store_url(store) if store else None,
                   shots=shots, segment_runs=segment_runs, max_attempts=max_attempts,
                   poll_interval_s=2.0)
    out = summary.result
    lines = [f"  shot {name}: {v['count']} frames -> {v['frames']}" for name, v in out["shots"].items()]
    _emit({**out, **summary.counts()}, json_out, "\n".join(lines) or None)


@app.command()
def truth(spec: SpecArg,
          shot: Annotated[str, typer.Option("--shot", help="the shot whose truth to render")],
          out: Annotated[Optional[Path], typer.Option("--out", help="also write the frames' EXRs into this folder")] = None,
          supersample: Annotated[int, typer.Option(min=1, help="samples per pixel side")] = 2,
          store: SpecStoreOpt = None, json_out: JsonOpt = False) -> None:
    """Render the truth of a shot over a synthetic capture: what its camera would have seen."""
    from flows.production import open_production
    from flows.truth import truth_capture, truth_flow

    url = _store_url(store) if store else None
    truth_capture(open_production(spec, url, [shot]), shot, spec)  # one line, before any flow runs
    start_api_early()
    summary = _run(truth_flow, spec=str(spec.resolve()), shot=shot, store=url, supersample=supersample)
    result = dict(summary.result)
    lines = [f"  truth of shot {shot}: {result['frames']} frames -> {result['ref']} ({result['truth']})"]
    if out is not None:
        s = _open(result["store"])
        paths = []
        for name, entry in sorted(s.get_tree(result["truth"]).items()):
            _write_atomic(out / name, s.get_bytes(entry.digest))
            paths.append(str(out / name))
        result["out"] = paths
        lines.append(f"  {len(paths)} EXR files in {out}")
    _emit({**result, **summary.counts()}, json_out, "\n".join(lines))


@app.command()
def worker(pool: Annotated[str, typer.Option(help="work pool: gpu (segments) or control (productions)")],
           name: Annotated[Optional[str], typer.Option(help="worker name (default: Prefect's)")] = None,
           limit: Annotated[Optional[int], typer.Option(help="flow runs at once (1 per GPU)")] = None,
           worker_type: Annotated[str, typer.Option("--type", help="worker type")] = "process") -> None:
    """Start a Prefect worker for POOL with volcap's settings (docs/operations.md); runs until stopped.

    One per GPU, each seeing only its GPU (CUDA_VISIBLE_DEVICES), with --limit 1: deploy/worker.sh
    does that for every GPU of a machine.
    """
    import os

    env_defaults = {"DO_NOT_TRACK": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
                    "PREFECT_FLOWS_HEARTBEAT_FREQUENCY": "60"}
    for k, v in env_defaults.items():
        os.environ.setdefault(k, v)
    if not os.environ.get("PREFECT_API_URL"):
        raise CommandError("PREFECT_API_URL is not set: a worker needs a Prefect server "
                           "(docs/operations.md, 1.)")
    args = [sys.executable, "-m", "prefect", "worker", "start", "--pool", pool, "--type", worker_type]
    if name:
        args += ["--name", name]
    if limit is not None:
        args += ["--limit", str(limit)]
    sys.stdout.flush()
    OUTPUT.native.stop()  # the worker gets the real stderr
    # A Prefect worker stops on SIGTERM by sending itself SIGINT and restoring the SIGINT handler it
    # found at start; started with SIGINT ignored (a background job of a non-interactive shell whose
    # own SIGINT was ignored, a CI runner), that handler is "ignore" and it never stops. An ignored
    # signal survives exec, a default one becomes Python's KeyboardInterrupt: reset it here.
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    os.execv(sys.executable, args)  # the worker replaces this process: signals reach it directly


def _split_verbose(argv: list[str]) -> tuple[list[str], bool]:
    """``--verbose`` anywhere before a ``--`` (global option or after the command) -> (rest, True)."""
    end = argv.index("--") if "--" in argv else len(argv)
    head = [a for a in argv[:end] if a != "--verbose"]
    env = os.environ.get("VOLCAP_VERBOSE", "").strip().lower() in ("1", "true", "yes", "on")
    return head + argv[end:], len(head) < end or env


def _command_words(args: list[str]) -> str:
    """What a cancellation line names: the command and its leading arguments (``calibrate
    captures/NAME``, ``store verify``), up to the first option."""
    words = []
    for a in args:
        if a.startswith("-") or len(words) == 3:
            break
        words.append(a)
    return " ".join(words) or "volcap"


def main() -> None:
    """Entry point: stderr is one line (the cause) for failed work, exit 1; flows/cli_output.py.

    First the process defaults (one OpenMP thread) while nothing has imported torch: every command,
    and through ``volcap worker``'s environment every flow run its worker starts."""
    reproducible_cpu_defaults()
    args, verbose = _split_verbose(sys.argv[1:])
    OUTPUT.start(verbose)
    from flows.runtime import stop_temporary_api

    if args[:1] != ["worker"]:  # the worker becomes Prefect's (exec): its own signal handling
        CANCEL.install(_command_words(args), OUTPUT.cancelled)  # SIGINT/SIGTERM: exit 130/143, one line
        CANCEL.before_exit(stop_temporary_api)
    try:
        code = app(args=args, standalone_mode=False)
        CANCEL.wait_if_cancelling()
        if isinstance(code, int) and code:  # typer returns (not raises) the code of an Exit
            sys.exit(code)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the command line's contract is one line and exit 1
        if hasattr(exc, "show") and isinstance(getattr(exc, "exit_code", None), int):
            exc.show()  # a click/typer usage or parameter error: exit 2, click's own message
            sys.exit(exc.exit_code)
        # a run Crashed by the signal reaches here while the watcher is still ending the process
        CANCEL.wait_if_cancelling(grace_s=1.0 if type(exc).__name__ == "CrashedRun" else 0.0)
        sys.exit(OUTPUT.report(exc))
    except SystemExit:
        raise
    except BaseException:  # Prefect's TerminationSignal on SIGTERM: the watcher ends the process
        CANCEL.wait_if_cancelling(grace_s=1.0)
        raise
    finally:
        OUTPUT.finish()  # Prefect's shutdown messages stay off the console (unless --verbose)


if __name__ == "__main__":
    main()
