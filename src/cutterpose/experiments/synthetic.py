"""The synthetic noise sweep of the seed paper (section 3.1, Fig. 5), run as ``PROTOCOL.md`` says.

Convention:
    Poses follow :mod:`cutterpose.geometry.pose` (``x_cam = R_cam_holder x_holder +
    t_cam_holder_mm``,
    ``R = Rz(gamma) Ry(beta) Rx(alpha)``). A trial draws alpha, beta, gamma uniformly in
    [-60, 60] deg and X, Y, Z - 600 uniformly in [-90, 90] mm, projects the holder's 20 corners
    through the pinhole camera of ``camera_synthetic.json``, redraws it if a corner leaves the
    image, and adds independent Gaussian noise of standard deviation sigma px to each coordinate.
    Every noise level has its own fixed seed (``SeedSequence([seed, round(1000 sigma)])``), so a
    level's trials do not depend on which other levels are run.

Correspondence-free methods (``initial``, ``dm``, ``dm+``) get the same noisy corners in contour
order with a random cyclic shift and a random direction, drawn per trial from the trial's own
seed: the result is the same for any number of worker processes.

The Cramer-Rao bound per DOF is ``sigma sqrt(diag((J^T J)^-1))`` with J the analytic Jacobian of
the 40 pixel coordinates with respect to (alpha, beta, gamma [deg], X, Y, Z [mm]); over random
poses the bound on the std is the root mean of the per-trial bound variances.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera, PinholeCamera, default_camera
from ..geometry.holder import Holder, default_holder, holder_from_dict
from ..geometry.pose import pixel_jacobian, rotation_from_euler_deg
from ..methods import Method, get_method
from ..parallel import JobRunner, run_jobs
from .report import summarize, trial_rows, write_summary, write_trials_csv

ANGLE_RANGE_DEG = 60.0
TRANS_RANGE_MM = 90.0
NOMINAL_Z_MM = 600.0


@dataclass
class Trials:
    """A set of trials in the protocol's exchange layout.

    Attributes
    ----------
    points_holder_mm : (N, 3) model points in model order.
    points_px : (T, N, 2) observed pixels, same order.
    R_cam_holder : (T, 3, 3) and t_cam_holder_mm : (T, 3) true poses.
    sigma_px : (T,) noise level each trial was made with.
    camera : the pinhole camera (``K``, image size).
    shift, reverse : (T,) the contour-order scrambling given to correspondence-free methods.
    """

    points_holder_mm: np.ndarray
    points_px: np.ndarray
    R_cam_holder: np.ndarray
    t_cam_holder_mm: np.ndarray
    sigma_px: np.ndarray
    camera: Camera
    shift: np.ndarray
    reverse: np.ndarray

    def __len__(self) -> int:
        return len(self.points_px)

    def save_npz(self, path) -> None:
        """Write the protocol's trial file (``.npz``)."""
        np.savez_compressed(path, points_holder_mm=self.points_holder_mm, points_px=self.points_px,
                            K=self.camera.K, image_size_px=np.array(self.camera.image_size_px),
                            R_cam_holder=self.R_cam_holder, t_cam_holder_mm=self.t_cam_holder_mm,
                            sigma_px=self.sigma_px)


def _scramble(n_trials: int, n_points: int, seed_seq: np.random.SeedSequence):
    rng = np.random.default_rng(seed_seq.spawn(1)[0])
    return rng.integers(0, n_points, n_trials), rng.random(n_trials) < 0.5


def level_seed(seed: int, sigma_px: float) -> np.random.SeedSequence:
    """The fixed seed of one noise level."""
    return np.random.SeedSequence([int(seed), int(round(1000 * float(sigma_px)))])


def generate_trials(n_trials: int, sigma_px: float, seed: int = 0, camera: Camera | None = None,
                    holder: Holder | None = None, angle_range_deg: float = ANGLE_RANGE_DEG,
                    trans_range_mm: float = TRANS_RANGE_MM,
                    nominal_z_mm: float = NOMINAL_Z_MM) -> Trials:
    """Draw ``n_trials`` protocol trials at one noise level (vectorised, with redraws).

    Parameters
    ----------
    n_trials : number of trials.
    sigma_px : standard deviation of the pixel noise per coordinate.
    seed : base seed; the level's seed is ``SeedSequence([seed, round(1000 sigma)])``.
    camera, holder : default ``camera_synthetic.json`` and ``holder.json``.
    """
    if n_trials < 0 or sigma_px < 0 or not math.isfinite(sigma_px):
        raise InputError("n_trials and sigma_px must be non-negative and finite")
    camera = camera or default_camera("synthetic")
    holder = holder or default_holder()
    P = holder.points_holder_mm
    ss = level_seed(seed, sigma_px)
    pose_ss, noise_ss, scramble_ss = ss.spawn(3)
    rng = np.random.default_rng(pose_ss)
    Rs, ts, pxs = [], [], []
    have = 0
    for _ in range(1000):
        if have >= n_trials:
            break
        m = max(16, int(1.3 * (n_trials - have)))
        ang = rng.uniform(-angle_range_deg, angle_range_deg, (m, 3))
        t = rng.uniform(-trans_range_mm, trans_range_mm, (m, 3)) + [0.0, 0.0, nominal_z_mm]
        R = rotation_from_euler_deg(ang[:, 0], ang[:, 1], ang[:, 2])
        X = np.einsum("tij,nj->tni", R, P) + t[:, None, :]
        px = camera.project(X)
        ok = np.all(camera.in_image(px) & (X[..., 2] > 0), axis=1)
        Rs.append(R[ok])
        ts.append(t[ok])
        pxs.append(px[ok])
        have += int(ok.sum())
    else:  # pragma: no cover - only with absurd ranges
        raise InputError("could not draw poses whose corners stay in the image")
    R = np.concatenate(Rs)[:n_trials]
    t = np.concatenate(ts)[:n_trials]
    px = np.concatenate(pxs)[:n_trials]
    noise = np.random.default_rng(noise_ss).normal(0.0, 1.0, px.shape) * sigma_px
    shift, reverse = _scramble(n_trials, len(P), scramble_ss)
    return Trials(P, px + noise, R, t, np.full(n_trials, float(sigma_px)), camera, shift, reverse)


def load_trials_file(path, seed: int = 0) -> Trials:
    """Read the protocol's trial file (``.npz``); see ``PROTOCOL.md``, "Exchange formats"."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: trial file not found")
    try:
        z = np.load(path)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not a readable .npz trial file ({e})") from None
    need = ["points_holder_mm", "points_px", "K", "image_size_px", "R_cam_holder",
            "t_cam_holder_mm", "sigma_px"]
    missing = [k for k in need if k not in z.files]
    if missing:
        raise InputError(f"{path}: missing array(s) {', '.join(missing)}")
    P = np.asarray(z["points_holder_mm"], float)
    px = np.asarray(z["points_px"], float)
    R = np.asarray(z["R_cam_holder"], float)
    t = np.asarray(z["t_cam_holder_mm"], float)
    sig = np.asarray(z["sigma_px"], float).ravel()
    T = len(px)
    if (P.ndim != 2 or P.shape[1] != 3 or px.shape != (T, len(P), 2) or R.shape != (T, 3, 3)
            or t.shape != (T, 3) or sig.shape != (T,)):
        raise InputError(f"{path}: inconsistent shapes: points_holder_mm {P.shape}, points_px "
                         f"{px.shape}, R_cam_holder {R.shape}, t_cam_holder_mm {t.shape}, "
                         f"sigma_px {sig.shape}")
    cam = PinholeCamera.from_matrix(z["K"], tuple(int(v) for v in z["image_size_px"]),
                                    name=f"K of {path.name}")
    shift, reverse = _scramble(T, len(P), np.random.SeedSequence([int(seed), 7919]))
    return Trials(P, px, R, t, sig, cam, shift, reverse)


def holder_for_points(points_holder_mm: np.ndarray) -> Holder | None:
    """A :class:`Holder` for model points given as an array (trial files), or None if the points
    are not a valid planar holder contour (then correspondence-free methods cannot run)."""
    ref = default_holder()
    P = np.asarray(points_holder_mm, float)
    if P.shape == ref.points_holder_mm.shape and np.allclose(P, ref.points_holder_mm):
        return ref
    try:
        c = P[:, :2]
        half = 0.625 * (c.max(axis=0) - c.min(axis=0)) + np.abs(c.mean(axis=0))
        return holder_from_dict({"inner_contour_corners": P.tolist(),
                                 "outer_rectangle": {"length_x": float(2 * half[0] + 1),
                                                     "width_y": float(2 * half[1] + 1)}},
                                where="trial file points_holder_mm")
    except Exception:  # noqa: BLE001 - any invalid contour just disables those methods
        return None


# ---------------------------------------------------------------------------------------------
# Cramer-Rao bound
def crlb_std(trials: Trials, sigma_px: float | None = None) -> np.ndarray:
    """The protocol's bound on the std per DOF: root mean over trials of the per-trial bound
    variances ``sigma^2 diag((J^T J)^-1)``; returns (6,)."""
    J = pixel_jacobian(trials.R_cam_holder, trials.t_cam_holder_mm, trials.points_holder_mm,
                       trials.camera.K)
    info = np.einsum("tki,tkj->tij", J, J)
    var = np.diagonal(np.linalg.inv(info), axis1=1, axis2=2)
    sig = trials.sigma_px if sigma_px is None else np.full(len(trials), sigma_px)
    return np.sqrt(np.mean(var * sig[:, None] ** 2, axis=0))


# ---------------------------------------------------------------------------------------------
# running methods over trials
def _solve_chunk(args):
    """Worker: run methods on a chunk of trials. Returns per method (R, t, time_ms, reasons)."""
    method_specs, cam, P, holder, px, shift, reverse = args
    out = {}
    for spec in method_specs:
        # registered methods travel by name (their solvers may be closures, not picklable)
        meth = get_method(spec) if isinstance(spec, str) else spec
        name = meth.name
        T = len(px)
        R = np.full((T, 3, 3), np.nan)
        t = np.full((T, 3), np.nan)
        tm = np.full(T, np.nan)
        reasons = [""] * T
        for i in range(T):
            pts = px[i]
            model = holder if holder is not None else P
            if not meth.needs_correspondences:
                if holder is None:
                    reasons[i] = "model points are not a holder contour"
                    continue
                order = np.roll(np.arange(len(pts)), -int(shift[i]))
                if reverse[i]:
                    order = order[::-1]
                pts = pts[order]
            t0 = time.perf_counter()
            try:
                est = meth.solve(pts, cam, model)
            except Exception as e:  # noqa: BLE001 - a failure is a result, counted in the table
                reasons[i] = f"{type(e).__name__}: {e}"
                tm[i] = (time.perf_counter() - t0) * 1e3
                continue
            tm[i] = (time.perf_counter() - t0) * 1e3
            if est:
                R[i], t[i] = est.R_cam_holder, est.t_cam_holder_mm
            else:
                reasons[i] = est.reason
        out[name] = (R, t, tm, reasons)
    return out


def _registered(name: str) -> bool:
    try:
        get_method(name)
    except InputError:
        return False
    return True


def run_trials(methods: list[Method], trials: Trials, workers: int = 1, progress=None,
               chunk: int = 25, scheduler=None, runner: JobRunner | None = None
               ) -> dict[str, tuple]:
    """Solve every trial with every method. Returns ``{name: (R, t, time_ms, reasons)}``.

    Chunks of ``chunk`` trials run where :mod:`cutterpose.parallel` puts them (this process,
    ``workers`` processes, the Dask cluster at ``scheduler``, or an open ``runner``). Results
    do not depend on that: every trial carries its own scrambling, methods are deterministic
    and the chunks are put back in trial order. ``progress(k)`` after each chunk of k trials.
    """
    holder = holder_for_points(trials.points_holder_mm)
    names = [m.name for m in methods]
    specs = [m.name if _registered(m.name) else m for m in methods]
    T = len(trials)
    jobs = [(specs, trials.camera, trials.points_holder_mm, holder, trials.points_px[i:i + chunk],
             trials.shift[i:i + chunk], trials.reverse[i:i + chunk]) for i in range(0, T, chunk)]
    done = (lambda i, _: progress(len(jobs[i][4]))) if progress else None
    parts = run_jobs(_solve_chunk, jobs, workers, scheduler, done, runner)
    out = {}
    for name in names:
        out[name] = tuple(
            np.concatenate([p[name][k] for p in parts]) if k < 3
            else sum((p[name][3] for p in parts), []) for k in range(4))
    return out


def parse_sigmas(spec: str) -> list[float]:
    """``"0:5:0.5"`` (start:stop:step, stop included) or ``"0,1,2.5"``."""
    try:
        if ":" in spec:
            a, b, s = (float(x) for x in spec.split(":"))
            if s <= 0:
                raise ValueError
            n = int(math.floor((b - a) / s + 1e-9)) + 1
            vals = [round(a + k * s, 10) for k in range(n)]
        else:
            vals = [float(x) for x in spec.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--sigmas: expected start:stop:step or a comma list, got {spec!r}") \
            from None
    if not vals or any(v < 0 or not math.isfinite(v) for v in vals):
        raise InputError(f"--sigmas: need non-negative noise levels, got {spec!r}")
    return vals


@dataclass
class SweepResult:
    rows: list
    stats: list
    crlb: dict
    out_dir: Path | None


def run_synthetic(methods: list[str] | list[Method], sigmas=(0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0,
                  3.5, 4.0, 4.5, 5.0), n_trials: int = 1000, out_dir=None, seed: int = 0,
                  workers: int = 1, trials_file=None, show_progress: bool = True,
                  plot: bool = True, scheduler=None) -> SweepResult:
    """Run the Fig. 5 sweep (or a trial file) through ``methods``.

    ``workers`` local processes, or the Dask cluster at ``scheduler`` (an address such as
    ``tcp://host:8786``): the rows are the same either way (:mod:`cutterpose.parallel`).

    Writes ``trials.csv``, ``summary.md``, ``summary.json`` and ``fig5.png`` to ``out_dir``
    when given.
    """
    meths = [m if isinstance(m, Method) else get_method(m) for m in methods]
    if trials_file is not None:
        all_trials = load_trials_file(trials_file, seed=seed)
        levels = []
        for s in sorted(set(np.round(all_trials.sigma_px, 6))):
            idx = np.flatnonzero(np.round(all_trials.sigma_px, 6) == s)
            levels.append((float(s), idx, _subset(all_trials, idx)))
    else:
        levels = []
        for s in sigmas:
            tr = generate_trials(n_trials, s, seed)
            levels.append((float(s), np.arange(n_trials), tr))
    total = sum(len(tr) for _, _, tr in levels) * len(meths)
    rows, crlb = [], {}
    with JobRunner(workers, scheduler) as runner:
        bar = _progress(total, show_progress)
        try:
            for s, idx, tr in levels:
                if bar:
                    bar.update(description=f"sigma {s:g} px ({runner.where})")
                res = run_trials(meths, tr, runner=runner,
                                 progress=(lambda k: bar.advance(k * len(meths))) if bar
                                 else None)
                if s > 0:
                    crlb[s] = crlb_std(tr, s).tolist()
                for m in meths:
                    R, t, tm, _ = res[m.name]
                    rows += trial_rows(idx, tr.sigma_px, m.name, tr.R_cam_holder,
                                       tr.t_cam_holder_mm, R, t, tm)
        finally:
            if bar:
                bar.close()
    stats = summarize(rows)
    out = None
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_trials_csv(rows, out / "trials.csv")
        n_desc = (f"trial file `{Path(trials_file).name}`" if trials_file
                  else f"{n_trials} trials per level, seed {seed}")
        write_summary(stats, out, crlb, title="Synthetic noise sweep (paper Fig. 5)",
                      notes=f"Methods: {', '.join(m.name for m in meths)}; {n_desc}. "
                            "Protocol: shared/spec/PROTOCOL.md.")
        if plot:
            from .plots import plot_fig5

            plot_fig5(stats, crlb, out / "fig5.png")
    return SweepResult(rows, stats, crlb, out)


def _subset(tr: Trials, idx) -> Trials:
    return Trials(tr.points_holder_mm, tr.points_px[idx], tr.R_cam_holder[idx],
                  tr.t_cam_holder_mm[idx], tr.sigma_px[idx], tr.camera, tr.shift[idx],
                  tr.reverse[idx])


class _Bar:
    def __init__(self, total):
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeRemainingColumn,
        )

        self.p = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                          TimeRemainingColumn(), console=Console(stderr=True), transient=False)
        self.p.start()
        self.task = self.p.add_task("solving", total=total)

    def update(self, description):
        self.p.update(self.task, description=description)

    def advance(self, k):
        self.p.advance(self.task, k)

    def close(self):
        self.p.stop()


def _progress(total, show):
    return _Bar(total) if show else None
