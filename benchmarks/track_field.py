"""Tracking on field-preset approach sequences (issue 13, item 2): per frame, the tracker and the
full measurement in the same run, on one core.

Input: folders written by ``cutterpose render-sequence`` (any engine and preset; the truth and
the camera come from their ``truth.json``). For every frame, in this order:

1. ``Tracker.update`` (CPU time of this process around it, and wall clock);
2. the full measurement ``measure`` (``--method``, default dm+b as the tracker's; the
   tracker's approach parameters and limits; ``--edge-break-mm 0`` declares the sharp edge of
   the analytic ``easy`` / ``field`` presets for ``dm+``, whose verdict otherwise carries an
   unknown break of up to 1.5 mm: 10 mm of depth at 900 mm, beyond the approach budget), timed
   the same way: its std per DOF is the frame's reference band, its CPU time the denominator of
   the speed ratio.

``--fps F`` plays the frames as a camera delivers them (frame ``i`` arrives at ``i / F`` s;
loaded into memory first; no full measurement in the loop): each frame's latency is from its
arrival to its answer (it waits while the tracker is busy with the one before), and the frames
answered later than ``1 / F`` after arrival are counted. ``--track anchor_lag=3`` defers the
``dm+b`` re-anchors (their band fits in a worker process; ``--anchor-worker thread`` or
``inline``: in a thread, or on the frame itself; the same poses); the tracker's CPU time is
then its own thread's. The clock starts when the tracker is ready (``Tracker.ready``: its
worker process started), as a live tracker is made before the approach begins. ``--newest``
plays a camera driver that drops stale frames instead of queueing them: when the tracker is
free it gets the newest frame that has arrived (with its time, ``update(..., t_s=)``), and
the ones before it are skipped (counted).

A tracked frame is *within the band* when every DOF's error (against the truth) is at most 3
std of the full measurement; where the full measurement refused the frame, the std of the
nearest frame whose full measurement was accepted is used (and said). Fall-backs are counted
with their reasons. A sequence with a jump (``"jump_at"`` in its truth) also reports the
recovery: the jump frame must fall back and say why, the next one be tracked.

Run it on one core (``taskset -c 0``; numpy/OpenCV single-threaded by the environment below):

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 taskset -c 0 \\
        python benchmarks/track_field.py SEQ_DIR [SEQ_DIR ...] --out results/track_field

Writes ``<out>/<name>/frames.csv`` per sequence and prints the summary.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from cutterpose.frames import load_frame
from cutterpose.geometry.camera import camera_from_dict
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.geometry.pose import pose_errors
from cutterpose.pipeline import DOF_NAMES, measure
from cutterpose.tracking import Tracker, TrackParams, approach_limits, approach_params

cv2.setNumThreads(1)


def run(seq: Path, with_full: bool = True, track: TrackParams | None = None,
        method: str = "dm+b", edge_look=None, edge_break_mm: float | None = None,
        fps: float | None = None, anchor_worker: str = "process",
        newest: bool = False) -> list[dict]:
    truth = json.loads((seq / "truth.json").read_text())
    camera = camera_from_dict(truth["camera"])
    holder = holder_from_dict(truth["holder"])
    params = approach_params(camera)
    limits = replace(approach_limits(), edge_break_mm=edge_break_mm)
    tracker = Tracker(camera, holder, method, limits=limits, filter=True, track=track,
                      edge_look=edge_look, anchor_worker=anchor_worker)
    rows = []
    frames = [load_frame(seq / e["file"]) for e in truth["images"]] if fps else None
    # a live tracker is made before the approach begins: its worker's start-up (~1-2 s) is
    # not in the played clock
    if not tracker.ready(60.0):
        print("  the tracker's worker process did not start", file=sys.stderr)
    t_start = time.perf_counter()
    images = truth["images"]
    i, skipped = 0, 0
    while i < len(images):
        e = images[i]
        img = frames[i] if fps else load_frame(seq / e["file"])
        R, t = np.array(e["R_cam_holder"]), np.array(e["t_cam_holder_mm"])
        if fps:   # the camera's frame i arrives at i / fps; a busy tracker makes it wait
            arrival = t_start + i / fps
            time.sleep(max(arrival - time.perf_counter(), 0.0))
        c0, w0 = time.thread_time(), time.perf_counter()
        r = tracker.update(img, t_s=i / fps if newest else None)
        cpu, wall = (time.thread_time() - c0) * 1e3, (time.perf_counter() - w0) * 1e3
        err = (pose_errors(R, t, r.pose.R, r.pose.t_mm).dof[0] if r.pose is not None
               else np.full(6, np.nan))
        row = {"frame": e["frame"], "z_mm": t[2], "mode": r.mode, "cpu_ms": cpu,
               "wall_ms": wall, "passes": r.passes, "lines_seen": r.lines_seen,
               "lines_dropped": r.lines_dropped, "rms_px": r.rms_px,
               "reason": r.fallback_reason, "anchor": r.anchor,
               "anchor_wait_ms": r.timings_ms.get("anchor_wait", 0.0),
               "full_wait_ms": r.timings_ms.get("full_wait", math.nan)}
        if fps:
            row["latency_ms"] = (time.perf_counter() - arrival) * 1e3
            row["fps"] = fps
            row["skipped_before"] = skipped
        row |= {f"err_{n}": v for n, v in zip(DOF_NAMES, err)}
        row |= {f"std_{n}": v for n, v in zip(DOF_NAMES, r.std_dof)}
        if r.anchor and "refused" in r.anchor:
            print(f"  {seq.name} frame {e['frame']}: {r.anchor}", file=sys.stderr)
        if with_full:
            c0 = time.process_time()
            m = measure(img, camera, holder, method, params, limits, edge_look=edge_look)
            row["full_cpu_ms"] = (time.process_time() - c0) * 1e3
            row["full_ok"] = bool(m.ok)
            ferr = (pose_errors(R, t, m.pose.R, m.pose.t_mm).dof[0] if m.pose is not None
                    else np.full(6, np.nan))
            row |= {f"full_std_{n}": v for n, v in zip(DOF_NAMES, m.std_dof)}
            row |= {f"full_err_{n}": v for n, v in zip(DOF_NAMES, ferr)}
            row["full_reason"] = "" if m.ok else m.quality.reason
        rows.append(row)
        print(f"  {seq.name} frame {e['frame']}: {r.mode} {cpu:.1f} ms", file=sys.stderr,
              flush=True)
        nxt = i + 1
        if newest:   # a driver that hands over the newest frame: those before it are skipped
            nxt = max(nxt, min(int((time.perf_counter() - t_start) * fps), len(images) - 1))
            skipped += nxt - i - 1
        i = nxt
    tracker.close()
    if with_full:
        band(rows)
    return rows


def band(rows: list[dict]) -> None:
    """Each tracked frame's |error| / std of the full measurement (its own, or the nearest
    accepted one's)."""
    ok = [i for i, r in enumerate(rows) if r["full_ok"]]
    for i, r in enumerate(rows):
        if not ok:
            r["band_from"], r["max_z"] = None, np.nan
            continue
        j = i if r["full_ok"] else min(ok, key=lambda k: abs(k - i))
        std = np.array([rows[j][f"full_std_{n}"] for n in DOF_NAMES])
        err = np.array([r[f"err_{n}"] for n in DOF_NAMES])
        z = np.abs(err) / std
        r["band_from"] = rows[j]["frame"]
        r["max_z"] = float(np.max(z))
        r["max_z_dof"] = DOF_NAMES[int(np.argmax(z))] if np.all(np.isfinite(z)) else ""
        r["in_band"] = bool(np.all(z <= 3.0))
        # the tracked pose against the full measurement of the same frame, in its std
        if r["full_ok"] and r["mode"] == "track":
            ferr = np.array([r[f"full_err_{n}"] for n in DOF_NAMES])
            r["max_dev_z"] = float(np.max(np.abs(err - ferr) / std))


def summary(name: str, rows: list[dict], truth: dict) -> None:
    """The run's lines: modes and speed of the tracked frames, the pace when played at a
    frame rate, the fall-backs, the accuracy against the full measurement, and the
    sequence's events (a jump, dropped frames)."""
    tr = [r for r in rows if r["mode"] == "track"]
    _tracked_lines(name, rows, tr)
    if "latency_ms" in rows[0]:
        _pace_lines(rows)
    _fallback_lines(rows)
    _accuracy_lines(rows, tr)
    _event_lines(rows, truth.get("sequence", {}))


def _tracked_lines(name: str, rows: list[dict], tr: list[dict]) -> None:
    modes = {m: sum(r["mode"] == m for r in rows) for m in ("track", "full", "lost")}
    print(f"{name}: {len(rows)} frames, {modes['track']} tracked, {modes['full']} full "
          f"(first + fall-backs), {modes['lost']} lost")
    if tr:
        cpu = np.array([r["cpu_ms"] for r in tr])
        print(f"  tracked: CPU median {np.median(cpu):.1f} ms (p90 {np.percentile(cpu, 90):.1f}, "
              f"max {cpu.max():.1f}), wall median {np.median([r['wall_ms'] for r in tr]):.1f} "
              f"ms; passes 1/2/3: {[sum(r['passes'] == p for r in tr) for p in (1, 2, 3)]}; "
              f"edges seen median {np.median([r['lines_seen'] for r in tr]):.0f} (min "
              f"{min(r['lines_seen'] for r in tr)}), edges dropped as outliers in "
              f"{sum(r['lines_dropped'] > 0 for r in tr)} frames")
        an = [r for r in tr if r["anchor"].startswith("re-anchored")]
        refused = [r for r in tr if "refused" in r["anchor"]]
        started = [r for r in tr if "re-anchor started" in r["anchor"]]
        if an or refused:
            plain = np.array([r["cpu_ms"] for r in tr
                              if not r["anchor"] or r["anchor_wait_ms"] > 0])
            print(f"  re-anchored on {len(an)} tracked frames "
                  f"({[r['frame'] for r in an]}), CPU median "
                  f"{np.median([r['cpu_ms'] for r in an]) if an else np.nan:.0f} ms; refused on "
                  f"{len(refused)} {[r['frame'] for r in refused]}; the other tracked frames: "
                  f"CPU median {np.median(plain):.1f} ms (p90 {np.percentile(plain, 90):.1f})")
        if started:
            wait = np.array([r["anchor_wait_ms"] for r in an])
            print(f"  deferred: started on {[r['frame'] for r in started]}; waited for at "
                  f"take-up median {np.median(wait) if len(wait) else np.nan:.1f} ms (max "
                  f"{wait.max() if len(wait) else np.nan:.1f})")


def _pace_lines(rows: list[dict]) -> None:
    lat = np.array([r["latency_ms"] for r in rows[1:]])
    fps = rows[0]["fps"]
    if rows[-1].get("skipped_before"):
        print(f"  newest-frame driver: {rows[-1]['skipped_before']} frames skipped, "
              f"{len(rows)} answered")
    print(f"  played at {fps:g} fps: latency after the first frame median "
          f"{np.median(lat):.1f} ms (p90 {np.percentile(lat, 90):.1f}, max {lat.max():.1f}); "
          f"answered later than one frame ({1e3 / fps:.0f} ms): {int(np.sum(lat > 1e3 / fps))}"
          f" of {len(lat)}")


def _fallback_lines(rows: list[dict]) -> None:
    # deferred fall-backs (TrackParams.defer_fallbacks with anchor_lag > 0): the frame has no
    # pose; those before the take-up are tracked meanwhile, or have none either
    started = [r for r in rows if r["reason"].endswith(")") and
               "full measurement started (applied at" in r["reason"]]
    pending = [r for r in rows if " pending (applied at frame" in r["reason"]]
    meanwhile = [r for r in rows if " pending (applied at frame" in r["anchor"]]
    taken = [r for r in rows if np.isfinite(r["full_wait_ms"])]
    if started or pending:
        wait = np.array([r["full_wait_ms"] for r in taken])
        print(f"  deferred fall-backs: started on {[r['frame'] for r in started]}; while "
              f"pending tracked {[r['frame'] for r in meanwhile]}, without a pose "
              f"{[r['frame'] for r in pending]}; taken up on "
              f"{[(r['frame'], r['mode']) for r in taken]}, waited for median "
              f"{np.median(wait) if len(wait) else np.nan:.1f} ms (max "
              f"{wait.max() if len(wait) else np.nan:.1f})")
    reasons: dict[str, list] = {}
    for r in rows[1:]:
        if r["mode"] != "track" and r not in pending:
            key = r["reason"].split(":")[0][:70]
            reasons.setdefault(key, []).append(r["frame"])
    for k, v in reasons.items():
        print(f"  fall-back x{len(v)} (frames {v}): {k}")


def _accuracy_lines(rows: list[dict], tr: list[dict]) -> None:
    if "full_ok" not in rows[0]:   # run without the full measurement (--no-full)
        return
    full_cpu = np.array([r["full_cpu_ms"] for r in rows])
    nok = sum(r["full_ok"] for r in rows)
    print(f"  full measurement: CPU median {np.median(full_cpu):.0f} ms, accepted on "
          f"{nok}/{len(rows)}")
    if tr:
        print(f"  ratio tracked / full (medians, same run): "
              f"{np.median([r['cpu_ms'] for r in tr]) / np.median(full_cpu):.3f}")
        zs = [r["max_z"] for r in tr]
        inb = sum(bool(r.get("in_band")) for r in tr)
        own = sum(r["band_from"] == r["frame"] for r in tr)
        print(f"  tracked frames within 3 std of the full measurement: {inb}/{len(tr)} "
              f"(band from the frame's own full measurement on {own}, the nearest accepted "
              f"one on the rest); largest |err|/std {np.nanmax(zs):.2f}")
        # and in the tracked pose's own std (the fit's and its anchor's, TrackResult.std_dof):
        # is the figure the robot gets with each tracked pose honest?
        own_z = np.array([max(abs(r[f"err_{n}"]) / r[f"std_{n}"] for n in DOF_NAMES)
                          for r in tr])
        print(f"  tracked frames within 3 of their own std: {int(np.sum(own_z <= 3.0))}/"
              f"{len(tr)}; largest |err|/std {np.nanmax(own_z):.2f}")
        dev = [r["max_dev_z"] for r in tr if "max_dev_z" in r]
        if dev:
            print(f"  |tracked - full pose| / std of the full measurement, same frame: median "
                  f"{np.median(dev):.2f}, largest {max(dev):.2f} (on {len(dev)} frames)")
        # the tracker's own std against the full measurement's, same frame
        ratio = np.array([[r[f"std_{n}"] / r[f"full_std_{n}"] for n in DOF_NAMES]
                          for r in tr if r["full_ok"]])
        if len(ratio):
            print("  tracked std / full std, same frame, median (max): " + ", ".join(
                f"{n} {m:.2f} ({x:.2f})" for n, m, x in
                zip(DOF_NAMES, np.nanmedian(ratio, axis=0), np.nanmax(ratio, axis=0))))
        for r in tr:
            if not r.get("in_band"):
                print(f"    outside: frame {r['frame']} {r['max_z_dof']} {r['max_z']:.2f} std "
                      f"(band from frame {r['band_from']})")
        e = np.array([[abs(r[f"err_{n}"]) for n in DOF_NAMES] for r in tr])
        fe = np.array([[abs(r[f"full_err_{n}"]) for n in DOF_NAMES] for r in tr
                       if r["full_ok"]])
        print("  largest |error| tracked: " + ", ".join(
            f"{n} {v:.3f}" for n, v in zip(DOF_NAMES, e.max(axis=0))))
        if len(fe):
            print("  largest |error| full (accepted, same frames): " + ", ".join(
                f"{n} {v:.3f}" for n, v in zip(DOF_NAMES, fe.max(axis=0))))


def _event_lines(rows: list[dict], seq: dict) -> None:
    if seq.get("jump_at") is not None:
        ja = seq["jump_at"]
        after = [r for r in rows if r["frame"] >= ja]
        if after:
            j = after[0]
            nxt = after[1]["mode"] if len(after) > 1 else "-"
            print(f"  jump at frame {ja}: {j['mode']} ({j['reason'][:90]}); next frame: {nxt}")
    if seq.get("dropped"):
        for d in seq["dropped"]:
            nx = [r for r in rows if r["frame"] > d][:1]
            if nx:
                print(f"  frame {d} dropped: frame {nx[0]['frame']} {nx[0]['mode']} "
                      f"({nx[0]['passes']} passes)")




def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("results/track_field"))
    ap.add_argument("--no-full", action="store_true", help="skip the full measurement")
    ap.add_argument("--method", default="dm+b", help="the tracker's and the reference full "
                    "measurement's pose method (dm+b, the default: the design edge, the "
                    "tracked frames carry its correction; dm+: the seen edge)")
    ap.add_argument("--edge-break-mm", type=float, default=None, help="the holders' edge "
                    "break for the corner methods' verdict (0: sharp, as the analytic easy "
                    "and field presets; default: not known)")
    ap.add_argument("--edge-look", default=None, help="an edge look file from "
                    "`cutterpose calibrate-edge-look` (dm+b: tracker and full measurement)")
    ap.add_argument("--newest", action="store_true", help="with --fps: hand the tracker the "
                    "newest frame when it is free (those that came meanwhile are skipped), "
                    "with the frames' times, as a camera driver that drops stale frames")
    ap.add_argument("--fps", type=float, default=None, help="play the frames at this rate "
                    "(a camera's; implies --no-full) and report each frame's latency")
    ap.add_argument("--anchor-worker", default="process", choices=("process", "thread",
                    "inline"), help="with anchor_lag > 0: where the re-anchors' band fits run "
                    "(the same poses with each)")
    ap.add_argument("--track", action="append", default=[], metavar="NAME=VALUE",
                    help="a TrackParams field (repeatable), e.g. max_rms_px=0.5")
    a = ap.parse_args()
    def number(v: str):
        if v.lower() in ("true", "false"):
            return v.lower() == "true"
        try:
            return int(v)
        except ValueError:
            return float(v)   # also "inf"

    tp = TrackParams(**{k: number(v) for k, v in (x.split("=", 1) for x in a.track)})
    for seq in a.sequences:
        look = None
        if a.edge_look:
            from cutterpose.calibration.edge_look import load_edge_look

            look = load_edge_look(a.edge_look)
        if a.newest and not a.fps:
            ap.error("--newest needs --fps")
        rows = run(seq, not (a.no_full or a.fps), tp, a.method, look, a.edge_break_mm,
                   a.fps, a.anchor_worker, a.newest)
        out = a.out / seq.name
        out.mkdir(parents=True, exist_ok=True)
        keys = list(dict.fromkeys(k for r in rows for k in r))
        with open(out / "frames.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, keys)
            w.writeheader()
            w.writerows(rows)
        truth = json.loads((seq / "truth.json").read_text())
        s = truth.get("sequence", {})
        print(f"\n{seq} ({s.get('engine')}, preset {', '.join(truth['presets'])}, {a.method}"
              f"{'' if a.edge_break_mm is None else f', edge break {a.edge_break_mm:g} mm'}"
              f"{', spp ' + str(s['spp']) if s.get('spp') else ''}; {s.get('z_start_mm')} -> "
              f"{s.get('z_end_mm')} mm)")
        summary(seq.name, rows, truth)
    return 0


if __name__ == "__main__":
    sys.exit(main())
