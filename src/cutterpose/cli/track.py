"""Tracking an approach frame by frame: ``track``."""

from __future__ import annotations

import typer

from .app import (
    app,
    camera_from_option,
    edge_break_option,
    edge_look_option,
    friendly,
    load_edge_look,
    log,
    pixel_format_option,
)

FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg", ".pgm", ".raw", ".mono8")


def _frames(source: str, raw_size, pixel_format=None):
    """(name, frame) of a folder of frames (sorted names) or of a video file."""
    from pathlib import Path

    from ..errors import InputError
    from ..frames import load_frame

    p = Path(source)
    if p.is_dir():
        files = sorted(q for q in p.iterdir() if q.suffix.lower() in FRAME_SUFFIXES)
        if not files:
            raise InputError(f"{p}: no frames ({', '.join(FRAME_SUFFIXES)})")
        for q in files:
            yield q.name, load_frame(q, raw_size=raw_size, pixel_format=pixel_format)
        return
    if not p.is_file():
        raise InputError(f"{p}: neither a folder of frames nor a video file")
    import cv2

    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise InputError(f"{p}: not a readable video")
    k = 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            yield f"{p.name}#{k}", frame
            k += 1
    finally:
        cap.release()
    if k == 0:
        raise InputError(f"{p}: the video has no frames")


@app.command("track")
@friendly
def track_cmd(
    source: str = typer.Argument(..., help="Folder of frames (sorted by name) or a video."),
    camera: str = typer.Option(None, help="table1 (default), synthetic, or a camera file."),
    holder: str = typer.Option(None, help="Holder JSON file (default: the bundled holder)."),
    method: str = typer.Option("dm+b", help="Pose method of the full measurement (first "
                               "frame and fall-backs; dm+b, the default: the tracked frames fit "
                               "the design edge of a broken edge, its offsets measured again by "
                               "a band fit as the view changes, 'anchor' per frame; dm+: the "
                               "seen edges, for a sharp edge (--edge-break-mm 0) or a binned "
                               "camera)."),
    raw: str = typer.Option(None, "--raw", help="Frames are raw files of WIDTHxHEIGHT."),
    pixel_format: str = pixel_format_option(),
    filter_: bool = typer.Option(False, "--filter", help="Also report a constant-velocity "
                                 "filtered pose (beside the raw one)."),
    json_lines: bool = typer.Option(False, "--json-lines", help="One JSON object per frame."),
    edge_break_mm: float = edge_break_option(),
    edge_look: str = edge_look_option(),
    anchor_lag: int = typer.Option(None, min=0, help="dm+b: run the re-anchors' band fits "
                                   "(~120 ms) beside the tracking and apply them this many "
                                   "frames later (0: on their frame, which waits; default: "
                                   "the tracker's); > 0 also measures a frame tracking "
                                   "cannot follow beside it (that frame has no pose and says "
                                   "so; the next ones are tracked meanwhile)."),
):
    """Track the holder through a sequence: edges predicted from the previous pose, the full
    measurement on the first frame and whenever tracking fails (said per frame)."""
    from dataclasses import replace

    import numpy as np

    from ..frames import parse_raw_size
    from ..station import build_station
    from ..tracking import Tracker, TrackParams, approach_limits, approach_params

    cam = camera_from_option(camera)
    station = build_station(cam, holder, method, params=approach_params(cam),
                            limits=replace(approach_limits(), edge_break_mm=edge_break_mm),
                            edge_look=load_edge_look(edge_look))
    tp = TrackParams() if anchor_lag is None else TrackParams(anchor_lag=anchor_lag)
    tracker = Tracker.from_station(station, filter=filter_, track=tp)
    size = parse_raw_size(raw) if raw else None
    modes, times, anchors, beside = {}, [], 0, 0
    with tracker:
        results = ((name, tracker.update(frame))
                   for name, frame in _frames(source, size, pixel_format))
        for name, r in results:
            _track_line(r, name, modes, times, json_lines)
            anchors += r.anchor.startswith("re-anchored")
            beside += "full measurement started (applied at frame" in r.fallback_reason
    med = f", tracking median {np.median(times):.1f} ms/frame" if times else ""
    log(f"{sum(modes.values())} frames: {modes.get('track', 0)} tracked, "
        f"{modes.get('full', 0)} full measurements (first + fall-backs), "
        f"{modes.get('lost', 0)} lost{med}"
        + (f"; {beside} fall-backs measured beside the tracking" if beside else "")
        + (f"; {anchors} re-anchored (band fit)" if anchors else ""))


def _track_line(r, name: str, modes: dict, times: list, json_lines: bool) -> None:
    """One frame of ``cutterpose track``: counted, and printed (a line, or JSON)."""
    import json as _json

    modes[r.mode] = modes.get(r.mode, 0) + 1
    if r.mode == "track":
        times.append(r.timings_ms["total"])
    if json_lines:
        typer.echo(_json.dumps({"file": name} | r.to_dict()))
        return
    pose = "  ".join(f"{v:8.3f}" for v in r.pose.dof) if r.pose is not None else "no pose"
    note = f"  ({r.fallback_reason})" if r.fallback_reason and r.frame else ""
    note += f"  ({r.anchor})" if r.anchor else ""
    typer.echo(f"{name:24s} {r.mode:5s} {pose}  {r.timings_ms['total']:6.1f} ms{note}")
